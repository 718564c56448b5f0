"""The decision every controller of the position/attitude loops returns, and their protocol.

EPC, the PD baseline and MPC-every-tick share one interface so the service, the simulator
and the benchmark can swap them: ``step(x0, refs, u_p=None, *, perturbation=None) ->
Decision`` (``u_p``: the nominal input, (nu,) or per stage (N, nu)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy.typing as npt

from epc_offboard.common.frames import FloatArray

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
    def step(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None = None,
        *,
        perturbation: npt.ArrayLike | None = None,
    ) -> Decision: ...
