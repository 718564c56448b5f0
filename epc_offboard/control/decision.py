"""The decision every controller of the position/attitude loops returns, and their protocol.

EPC, the PD baseline and MPC-every-tick share one interface so the service, the simulator
and the benchmark can swap them: ``step(x0, refs, u_p=None, *, perturbation=None) ->
Decision`` (``u_p``: the nominal input, (nu,) or per stage (N, nu)), written once, in
:class:`Controller`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy.typing as npt

from epc_offboard.common.frames import FloatArray
from epc_offboard.control.qp import MpcProblem

# hit: a stored controller passed the KKT check; solved: the exact QP optimum was computed
# this tick (for PD: its control law was evaluated — PD has no library and always "solves");
# intermediate: the short-horizon slack QP; fallback: a bounded hover command.
Source = Literal["hit", "solved", "intermediate", "fallback"]


@dataclass(frozen=True)
class Decision:
    """One tick's output. ``u`` (nu,) absolute input; ``compute_us`` wall time of the step;
    ``x_pred`` (N, nx) predicted states x_1..x_N when the method has them cheaply."""

    u: FloatArray
    source: Source
    compute_us: float
    x_pred: FloatArray | None = None


class Controller(Protocol):
    """What every controller of the loops is (EPC, PD, MPC-every-tick): the ONE place the
    ``step`` signature is written. Implementations subclass it and write :meth:`decide`;
    ``step`` stacks the QP's parameter vector θ (:meth:`MpcProblem.theta
    <epc_offboard.control.qp.MpcProblem.theta>`) once for all of them."""

    problem: MpcProblem

    def step(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None = None,
        *,
        perturbation: npt.ArrayLike | None = None,
    ) -> Decision:
        """One control tick. ``x0`` (nx,), ``refs`` (N, nx) absolute references for
        x_1..x_N, ``u_p`` (nu,) or (N, nu) nominal input, ``perturbation`` p^ (nx,) added to
        the model offset. With a perturbation and no ``u_p``, ``u_p = -pinv(B) p^`` (the
        input cancelling it)."""
        t0 = time.perf_counter()
        theta = self.theta_compiled(x0, refs, u_p, perturbation)
        if theta is None:
            theta = self.problem.theta(x0, refs, u_p, perturbation=perturbation,
                                       out=self.theta_buffer())  # fmt: skip
        return self.decide(theta, t0)

    def theta_compiled(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None,
        perturbation: npt.ArrayLike | None,
    ) -> FloatArray | None:
        """θ stacked by a compiled kernel where a controller has one and the arguments suit
        it, bit for bit :meth:`MpcProblem.theta`'s; None: ``problem.theta`` stacks it."""
        return None

    def check_args(self) -> tuple[Any, ...] | None:
        """The arguments of a compiled θ stack with the last controller's check
        (``kernels.theta_check``'s after x0, refs and u_p, the perturbation between its
        first and second) where a controller has one; None: it has none (the caller calls
        :meth:`step`)."""
        return None

    def checked(self, hit: int, check: tuple[Any, ...]) -> FloatArray | None:
        """θ, once a compiled call with :meth:`check_args`' ``check`` stacked it and made
        the check (``hit``: its answer); None: not stacked (the caller calls :meth:`step`)."""
        return None

    def theta_buffer(self) -> FloatArray | None:
        """Where :meth:`step` writes θ (None: a new array each tick)."""
        return None

    def decide(self, theta: FloatArray, t0: float) -> Decision:
        """The tick's decision at θ (nθ,); ``t0``: the step's start (``time.perf_counter``)."""
        ...


def elapsed_us(t0: float) -> float:
    """Microseconds since ``t0`` (``time.perf_counter``): a decision's ``compute_us``."""
    return (time.perf_counter() - t0) * 1e6
