"""The condensed MPC quadratic program of thesis 3.1.2 and an OSQP wrapper with a lifecycle.

Over a horizon of N steps, with stacked inputs ``U = [u_0; ...; u_{N-1}]`` (N nu,) and
predicted states ``X = [x_1; ...; x_N]`` (N nx,)::

    X = Phi x0 + Bbar U + Psi c~           Phi = [A; A²; ...], Psi = [I; A + I; ...]
    min_U  1/2 (X - r)' Qbar (X - r) + 1/2 (U - U_p)' Rbar (U - U_p)
    s.t.   x_min <= x_k <= x_max (k = 1..N),  u_min <= u_k <= u_max (k = 0..N-1),
           P u_k <= p (k = 0..N-1, an optional input polytope)

which condenses to ``min 1/2 U' H U + h' U  s.t.  Gamma U <= gamma``. Everything that varies
from tick to tick is collected in one parameter vector::

    theta = [x0 (nx); r_1..r_N (N nx); c~ (nx); U_p = u_p,0..u_p,N-1 (N nu)]

``U_p`` is the nominal input per stage (thesis 3.1.2 stacks ``u_p0..u_p,N-1``): the input that
keeps the model on its reference (trajectory feedforward) and cancels the perturbation, so
the input penalty does not fight either. A single ``u_p`` (nu,) is repeated over the horizon.

and both vectors are affine in it: ``h = F theta`` and ``gamma = g0 + S theta``. That is what
lets EPC precompute one affine map per active set (thesis 3.6-3.8).

Constraint rows (the "layout" active sets index into), infinite bounds dropped, in order:
state upper bounds (k = 1..N, i = 0..nx-1), state lower bounds, input upper bounds
(k = 0..N-1, i = 0..nu-1), input lower bounds, input polytope rows (k = 0..N-1, j = 0..m_p-1).
"""

from __future__ import annotations

import contextlib
import copy
import enum
import hashlib
import logging
import math
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import osqp
import scipy.sparse as sp

from epc_offboard.common.errors import EpcError
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.models import LinearModel

logger = logging.getLogger(__name__)


class ProblemError(EpcError, ValueError):
    """An MPC problem is ill-posed: shapes, weights or bounds are inconsistent."""


@dataclass(frozen=True)
class ConstraintRow:
    """What one row of ``Gamma U <= gamma`` bounds: ``kind`` "x", "u" (a bound) or "up" (a row
    of the input polytope), stage, index (of the state, input or polytope row), side."""

    kind: str
    stage: int
    index: int
    upper: bool


def _weight(name: str, w: npt.ArrayLike, n: int, *, definite: bool) -> FloatArray:
    m = np.array(w, dtype=np.float64)
    if m.ndim == 1:
        m = np.diag(m)
    if m.shape != (n, n):
        raise ProblemError(f"{name} must be ({n}, {n}) or ({n},), got shape {m.shape}")
    if not np.all(np.isfinite(m)) or not np.allclose(m, m.T, atol=1e-12):
        raise ProblemError(f"{name} must be finite and symmetric")
    eig_min = float(np.linalg.eigvalsh(m).min())
    if eig_min < -1e-12 or (definite and eig_min <= 1e-12):
        kind = "positive definite" if definite else "positive semidefinite"
        raise ProblemError(f"{name} must be {kind}, smallest eigenvalue {eig_min:g}")
    return m


def _bound(name: str, b: npt.ArrayLike | None, n: int, fill: float) -> FloatArray:
    if b is None:
        return np.full(n, fill)
    v = np.array(b, dtype=np.float64).reshape(-1)
    if v.shape != (n,):
        raise ProblemError(f"{name} must have shape ({n},), got {v.shape}")
    if np.any(np.isnan(v)):
        raise ProblemError(f"{name} has NaN entries (use +-inf for unbounded)")
    return v


class MpcProblem:
    """The condensed QP of one loop (thesis 3.1.2); immutable once built.

    ``Q`` (nx, nx) or its diagonal, ``R`` (nu, nu) or its diagonal; bounds (nx,) / (nu,) with
    +-inf where unbounded; ``u_poly = (P (m_p, nu), p (m_p,))`` an input polytope every
    stage's input must also satisfy (``P u <= p``; e.g. a tilt cone's inner polygon).
    Matrices: ``H`` (nU, nU), ``F`` (nU, ntheta), ``G`` (m, nU),
    ``g0`` (m,), ``S`` (m, ntheta), with nU = N nu and m the number of finite bounds.
    """

    def __init__(
        self,
        model: LinearModel,
        *,
        horizon: int,
        Q: npt.ArrayLike,
        R: npt.ArrayLike,
        x_min: npt.ArrayLike | None = None,
        x_max: npt.ArrayLike | None = None,
        u_min: npt.ArrayLike | None = None,
        u_max: npt.ArrayLike | None = None,
        u_poly: tuple[npt.ArrayLike, npt.ArrayLike] | None = None,
        lead: tuple[npt.ArrayLike, npt.ArrayLike] | None = None,
        lead_stages: int | None = None,
    ) -> None:
        if not isinstance(horizon, int) or horizon < 1:
            raise ProblemError(f"horizon must be an integer >= 1, got {horizon!r}")
        nx, nu, N = model.nx, model.nu, horizon
        self.model = model
        self.horizon = N
        self.nx, self.nu = nx, nu
        self.Q = _weight("Q", Q, nx, definite=False)
        self.R = _weight("R", R, nu, definite=True)
        self.x_min = _bound("x_min", x_min, nx, -math.inf)
        self.x_max = _bound("x_max", x_max, nx, math.inf)
        self.u_min = _bound("u_min", u_min, nu, -math.inf)
        self.u_max = _bound("u_max", u_max, nu, math.inf)
        if np.any(self.x_min > self.x_max):
            raise ProblemError("x_min must be <= x_max")
        if np.any(self.u_min > self.u_max):
            raise ProblemError("u_min must be <= u_max (the input box must be non-empty)")
        self.u_poly_P = np.zeros((0, nu))
        self.u_poly_p = np.zeros(0)
        if u_poly is not None:
            P = np.array(u_poly[0], dtype=np.float64)
            pv = np.array(u_poly[1], dtype=np.float64).reshape(-1)
            if P.ndim != 2 or P.shape[1] != nu or pv.shape != (P.shape[0],):
                raise ProblemError(
                    f"u_poly must be (P (m, {nu}), p (m,)), got {P.shape} and {pv.shape}"
                )
            if not (np.all(np.isfinite(P)) and np.all(np.isfinite(pv))):
                raise ProblemError("u_poly must be finite")
            self.u_poly_P, self.u_poly_p = P, pv
        # lead = (j (nu,) state indices, b (nu,)): |u_k,i - x_k,j_i| <= b_i, k = 0..N-1
        self.lead_state = np.full(nu, -1, dtype=np.intp)
        self.lead_max = np.full(nu, math.inf)
        if lead is not None:
            js = np.array(lead[0], dtype=np.intp).reshape(-1)
            bs = _bound("lead bound", lead[1], nu, math.inf)
            if js.shape != (nu,) or np.any((js < 0) | (js >= nx)):
                raise ProblemError(f"lead's state indices must be ({nu},) in 0..{nx - 1}")
            if np.any(bs <= 0.0):
                raise ProblemError("lead bounds must be > 0")
            self.lead_state, self.lead_max = js, bs
        self.lead_stages = N if lead_stages is None else min(lead_stages, N)
        if self.lead_stages < 1:
            raise ProblemError(f"lead_stages must be >= 1, got {lead_stages}")
        self.n_u = N * nu
        self.n_theta = nx + N * nx + nx + N * nu
        self.i_up = nx + N * nx + nx  # where U_p starts inside theta
        self._pinv_b = np.asarray(np.linalg.pinv(model.B), dtype=np.float64)
        self._build()

    # -- construction ---------------------------------------------------------------------

    def _build(self) -> None:
        A, B = self.model.A, self.model.B
        nx, nu, N = self.nx, self.nu, self.horizon
        powers = [np.eye(nx)]
        for _ in range(N):
            powers.append(A @ powers[-1])
        self.Phi = np.vstack(powers[1:])  # (N nx, nx)
        self.Psi = np.vstack([sum(powers[: k + 1]) for k in range(N)])  # (N nx, nx)
        Bbar = np.zeros((N * nx, N * nu))
        for k in range(N):
            for j in range(k + 1):
                Bbar[k * nx : (k + 1) * nx, j * nu : (j + 1) * nu] = powers[k - j] @ B
        self.Bbar = Bbar
        Qbar = np.kron(np.eye(N), self.Q)
        Rbar = np.kron(np.eye(N), self.R)
        BtQ = Bbar.T @ Qbar
        self.H = BtQ @ Bbar + Rbar
        self.H = 0.5 * (self.H + self.H.T)
        # h = Bbar' Qbar (Phi x0 + Psi c - r) - Rbar U_p = F theta
        self.F = np.hstack([BtQ @ self.Phi, -BtQ, BtQ @ self.Psi, -Rbar])

        i_x0, i_c = 0, nx + N * nx
        rows_g: list[FloatArray] = []
        rows_s: list[FloatArray] = []
        g0: list[float] = []
        labels: list[ConstraintRow] = []

        def add_state_rows(bound: FloatArray, sign: float, upper: bool) -> None:
            for k in range(N):
                for i in range(nx):
                    if not math.isfinite(bound[i]):
                        continue
                    r = k * nx + i
                    s = np.zeros(self.n_theta)
                    s[i_x0 : i_x0 + nx] = -sign * self.Phi[r]
                    s[i_c : i_c + nx] = -sign * self.Psi[r]
                    rows_g.append(sign * Bbar[r])
                    rows_s.append(s)
                    g0.append(sign * bound[i])
                    labels.append(ConstraintRow("x", k + 1, i, upper))

        def add_input_rows(bound: FloatArray, sign: float, upper: bool) -> None:
            for k in range(N):
                for i in range(nu):
                    if not math.isfinite(bound[i]):
                        continue
                    g = np.zeros(N * nu)
                    g[k * nu + i] = sign
                    rows_g.append(g)
                    rows_s.append(np.zeros(self.n_theta))
                    g0.append(sign * bound[i])
                    labels.append(ConstraintRow("u", k, i, upper))

        add_state_rows(self.x_max, 1.0, True)
        add_state_rows(self.x_min, -1.0, False)
        add_input_rows(self.u_max, 1.0, True)
        add_input_rows(self.u_min, -1.0, False)
        for sign, upper in ((1.0, True), (-1.0, False)):
            for k in range(self.lead_stages):
                for i in range(nu):
                    if not math.isfinite(self.lead_max[i]):
                        continue
                    j = int(self.lead_state[i])
                    g = np.zeros(N * nu)
                    g[k * nu + i] = sign
                    s = np.zeros(self.n_theta)
                    if k == 0:
                        s[i_x0 + j] = sign
                    else:
                        r = (k - 1) * nx + j
                        g -= sign * Bbar[r]
                        s[i_x0 : i_x0 + nx] = sign * self.Phi[r]
                        s[i_c : i_c + nx] = sign * self.Psi[r]
                    rows_g.append(g)
                    rows_s.append(s)
                    g0.append(float(self.lead_max[i]))
                    labels.append(ConstraintRow("lead", k, i, upper))
        for k in range(N):
            for j, (row, bound) in enumerate(zip(self.u_poly_P, self.u_poly_p, strict=True)):
                g = np.zeros(N * nu)
                g[k * nu : (k + 1) * nu] = row
                rows_g.append(g)
                rows_s.append(np.zeros(self.n_theta))
                g0.append(float(bound))
                labels.append(ConstraintRow("up", k, j, True))
        m = len(labels)
        self.G = np.array(rows_g).reshape(m, N * nu)
        self.S = np.array(rows_s).reshape(m, self.n_theta)
        self.g0 = np.array(g0, dtype=np.float64)
        self.rows: tuple[ConstraintRow, ...] = tuple(labels)
        self.n_con = m

    def with_model(self, model: LinearModel) -> MpcProblem:
        """The same problem (weights, bounds, horizon) over another model of equal size."""
        if (model.nx, model.nu) != (self.nx, self.nu):
            raise ProblemError(
                f"model size ({model.nx}, {model.nu}) differs from ({self.nx}, {self.nu})"
            )
        return self._replace(model, self.horizon)

    def with_horizon(self, horizon: int) -> MpcProblem:
        """The same problem over another horizon (the intermediate controller's)."""
        return self._replace(self.model, horizon)

    def _replace(self, model: LinearModel, horizon: int) -> MpcProblem:
        return MpcProblem(
            model,
            horizon=horizon,
            Q=self.Q,
            R=self.R,
            x_min=self.x_min,
            x_max=self.x_max,
            u_min=self.u_min,
            u_max=self.u_max,
            u_poly=(self.u_poly_P, self.u_poly_p) if len(self.u_poly_p) else None,
            lead=(self.lead_state, self.lead_max) if np.isfinite(self.lead_max).any() else None,
            lead_stages=self.lead_stages,
        )

    # -- per tick -------------------------------------------------------------------------

    def theta(
        self,
        x0: npt.ArrayLike,
        refs: npt.ArrayLike,
        u_p: npt.ArrayLike | None = None,
        *,
        perturbation: npt.ArrayLike | None = None,
        out: FloatArray | None = None,
    ) -> FloatArray:
        """Stack the parameter vector (written into ``out`` when given, to spare allocation).

        ``x0`` (nx,); ``refs`` (N, nx) absolute references for x_1..x_N; ``perturbation`` p^
        (nx,) makes ``c~ = c + p^``; ``u_p`` (nu,) for every stage or (N, nu) per stage,
        defaults to the input cancelling p^, ``-pinv(B) p^`` (zero without a perturbation).
        """
        nx, N = self.nx, self.horizon
        x = np.asarray(x0, dtype=np.float64)
        r = np.asarray(refs, dtype=np.float64)
        if x.shape != (nx,) or r.shape != (N, nx):
            raise ProblemError(
                f"expected x0 ({nx},) and refs ({N}, {nx}), got {x.shape} and {r.shape}"
            )
        th = np.empty(self.n_theta) if out is None else out
        th[:nx] = x
        th[nx : nx + N * nx] = r.reshape(-1)
        c0 = nx + N * nx
        up = th[self.i_up :].reshape(N, self.nu)
        if perturbation is None:
            th[c0 : c0 + nx] = self.model.c
            if u_p is None:
                up[:] = 0.0
        else:
            pert = np.asarray(perturbation, dtype=np.float64)
            if pert.shape != (nx,):
                raise ProblemError(f"perturbation must have shape ({nx},), got {pert.shape}")
            th[c0 : c0 + nx] = self.model.c + pert
            if u_p is None:
                up[:] = -(self._pinv_b @ pert)
        if u_p is not None:
            u = np.asarray(u_p, dtype=np.float64)
            if u.shape not in ((self.nu,), (N, self.nu)):
                raise ProblemError(
                    f"u_p must have shape ({self.nu},) or ({N}, {self.nu}), got {u.shape}"
                )
            up[:] = u
        return th

    def u_p(self, theta: FloatArray) -> FloatArray:
        """The first stage's nominal input ``u_p,0`` (nu,) inside ``theta``."""
        return theta[self.i_up : self.i_up + self.nu]

    def u_p_stages(self, theta: FloatArray) -> FloatArray:
        """Every stage's nominal input, (N, nu), a view into ``theta``."""
        return theta[self.i_up :].reshape(self.horizon, self.nu)

    def clip_input(self, u: FloatArray) -> FloatArray:
        """``u`` (nu,) clipped into the input box (a new array); the polytope is the caller's
        (an exact solution satisfies it; a degraded input is made safe downstream)."""
        out: FloatArray = np.minimum(np.maximum(u, self.u_min), self.u_max)
        return out

    def hover_input(self, theta: FloatArray) -> FloatArray:
        """The bounded hover command every controller degrades to: ``u_p`` (zero, or the
        input cancelling p^), clipped into the input box; NaN entries become zero."""
        return self.clip_input(np.nan_to_num(self.u_p(theta)))

    def with_offset(self, model: LinearModel) -> MpcProblem:
        """This problem over ``model``, which differs from the current one only in ``c``.

        Cheap (no matrix is rebuilt): ``c`` enters the QP only through ``theta``.
        """
        if not (np.array_equal(model.A, self.model.A) and np.array_equal(model.B, self.model.B)):
            raise ProblemError("with_offset needs the same A and B; use with_model")
        out = copy.copy(self)
        out.model = model
        return out

    def vectors(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(h, gamma)`` of the condensed QP at ``theta``."""
        return self.F @ theta, self.g0 + self.S @ theta

    def predict(self, theta: FloatArray, U: FloatArray) -> FloatArray:
        """Predicted states x_1..x_N, shape (N, nx), for stacked inputs ``U`` (N nu,)."""
        nx, N = self.nx, self.horizon
        x0 = theta[:nx]
        c = theta[nx + N * nx : 2 * nx + N * nx]
        out: FloatArray = (self.Phi @ x0 + self.Bbar @ U + self.Psi @ c).reshape(N, nx)
        return out

    def cost(self, theta: FloatArray, U: FloatArray) -> float:
        """``1/2 U' H U + h' U`` (the condensed objective without its constant)."""
        h = self.F @ theta
        return float(0.5 * U @ self.H @ U + h @ U)

    def signature(self) -> str:
        """Hex digest of everything that fixes the layout active sets index into.

        Horizon, prediction step, A, B, Q, R and which bounds are finite (the row layout):
        controllers are exchanged only between problems with equal signatures. Bound values
        and c are not included: a stored active set stays a valid *candidate* when they change
        and the KKT check decides whether it applies.
        """
        h = hashlib.sha256()
        h.update(f"epc-qp-v1;N={self.horizon};nx={self.nx};nu={self.nu};".encode())
        h.update(f"dt={self.model.dt_s!r};".encode())
        for name, arr in (("A", self.model.A), ("B", self.model.B), ("Q", self.Q), ("R", self.R)):
            h.update(name.encode())
            h.update(np.round(arr, 12).astype("<f8").tobytes())
        for name, b in (("xl", self.x_min), ("xu", self.x_max), ("ul", self.u_min),
                        ("uu", self.u_max)):
            h.update(name.encode())
            h.update(np.isfinite(b).astype("u1").tobytes())
        if np.isfinite(self.lead_max).any():
            h.update(b"lead")
            h.update(self.lead_state.astype("<i8").tobytes())
            h.update(np.isfinite(self.lead_max).astype("u1").tobytes())
            h.update(f"K={self.lead_stages};".encode())
        if len(self.u_poly_p):  # only problems with a polytope: old signatures stay valid
            h.update(b"up")
            h.update(np.round(self.u_poly_P, 12).astype("<f8").tobytes())
        return h.hexdigest()[:32]


# -- OSQP -----------------------------------------------------------------------------------


class QpStatus(enum.Enum):
    SOLVED = "solved"
    INACCURATE = "solved_inaccurate"
    INFEASIBLE = "infeasible"
    MAX_ITER = "max_iter"
    FAILED = "failed"


@dataclass(frozen=True)
class QpResult:
    """A solve's outcome: primal ``x``, duals ``y`` (one per row, > 0 on an active upper
    bound), whether polishing succeeded, iterations and status."""

    status: QpStatus
    x: FloatArray
    y: FloatArray
    polished: bool
    iterations: int

    @property
    def ok(self) -> bool:
        return self.status is QpStatus.SOLVED


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence C-level writes to fd 1 (OSQP prints while polishing even with verbose off)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        fd = 1
    sys.stdout.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


_STATUS = {
    1: QpStatus.SOLVED,
    2: QpStatus.INACCURATE,
    3: QpStatus.INFEASIBLE,
    4: QpStatus.INFEASIBLE,
    7: QpStatus.MAX_ITER,
}


class OsqpSolver:
    """``min 1/2 x' P x + q' x  s.t.  l <= A x <= u`` with a fixed ``P`` and ``A``.

    Lifecycle: construct (set up and factor once), then per tick ``solve(q, u, l)`` which
    updates the vectors and solves warm-started from the previous solution.
    """

    def __init__(
        self,
        P: FloatArray,
        A: FloatArray,
        *,
        polish: bool = True,
        eps_abs: float = 1e-8,
        eps_rel: float = 1e-8,
        max_iter: int = 10000,
    ) -> None:
        n, m = P.shape[0], A.shape[0]
        self.n, self.m = n, m
        self._polish = polish
        self._solver = osqp.OSQP()
        self._lower = np.full(m, -np.inf)
        self._solver.setup(
            sp.csc_matrix(np.triu(P)),
            np.zeros(n),
            sp.csc_matrix(A.reshape(m, n)),
            self._lower,
            np.full(m, np.inf),
            verbose=False,
            polishing=polish,
            polish_refine_iter=5,
            eps_abs=eps_abs,
            eps_rel=eps_rel,
            max_iter=max_iter,
            warm_starting=True,
        )

    def set_tolerances(self, eps_abs: float, eps_rel: float, max_iter: int) -> None:
        """Change the termination tolerances (kept for later solves)."""
        self._solver.update_settings(eps_abs=eps_abs, eps_rel=eps_rel, max_iter=max_iter)

    def solve(
        self, q: FloatArray, u: FloatArray, l: FloatArray | None = None  # noqa: E741
    ) -> QpResult:
        lower = self._lower if l is None else l
        self._solver.update(q=q, l=lower, u=u)
        if self._polish:
            with _quiet_stdout():
                res = self._solver.solve(raise_error=False)
        else:
            res = self._solver.solve(raise_error=False)
        status = _STATUS.get(int(res.info.status_val), QpStatus.FAILED)
        x = np.array(res.x, dtype=np.float64) if res.x is not None else np.full(self.n, np.nan)
        y = np.array(res.y, dtype=np.float64) if res.y is not None else np.full(self.m, np.nan)
        if status is QpStatus.SOLVED and not np.all(np.isfinite(x)):
            status = QpStatus.FAILED
        polished = int(getattr(res.info, "status_polish", 0)) == 1
        return QpResult(status, x, y, polished, int(res.info.iter))
