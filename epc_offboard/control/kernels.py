"""The EPC hit path's inner loops: apply cached active-set maps and KKT-check them.

``apply_map(M, width, theta_aug, n_check, u_out, u_min, u_max) -> bool`` computes
``w = M theta_aug`` row by row; the first ``n_check`` rows must satisfy ``0 <= w <= width``
(the KKT check, see :class:`epc_offboard.control.epc.maps.ActiveSetMap`), the last ``nu``
rows are the first input, written clipped to ``[u_min, u_max]`` into ``u_out`` when the check
passes.

Compiled with numba when it is installed: one call instead of five numpy calls, and an early
exit on the first violated row, which makes refusing a candidate cheaper than applying it.
The numpy version below is the reference and the fallback; the tests run both.

``query_maps(Ms, widths, n_checks, order, n_order, theta_aug, u_out, u_min, u_max) -> int``
is the library scan in one call: it tries the maps ``Ms[order[k]]`` for k = 0..n_order-1 in
that order and returns the first k whose check passes (its input written to ``u_out``), or
-1. ``n_order`` is the query's budget: the number of candidates checked never exceeds it.
"""

from __future__ import annotations

from collections.abc import Callable, MutableSequence, Sequence
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from epc_offboard.common import jit
from epc_offboard.common.frames import FloatArray

IntArray = npt.NDArray[np.int64]

ApplyMap = Callable[[FloatArray, FloatArray, FloatArray, int, FloatArray, FloatArray,
                     FloatArray], bool]
# (Ms, widths, n_checks, order, n_order, theta_aug, u_out, u_min, u_max) -> k or -1
QueryMaps = Callable[[Sequence[FloatArray], Sequence[FloatArray], IntArray, IntArray, int,
                      FloatArray, FloatArray, FloatArray, FloatArray], int]


def apply_map_numpy(
    M: FloatArray,
    width: FloatArray,
    theta_aug: FloatArray,
    n_check: int,
    u_out: FloatArray,
    u_min: FloatArray,
    u_max: FloatArray,
) -> bool:
    w = M @ theta_aug
    chk = w[:n_check]
    # chk >= 0 and chk <= width in one comparison: a non-negative double orders like its bits
    # as an unsigned integer; a negative one (sign bit set) or NaN compares above any width
    if not (chk.view(np.uint64) <= width.view(np.uint64)).all():
        return False
    np.minimum(w[n_check:], u_max, out=u_out)
    np.maximum(u_out, u_min, out=u_out)
    return True


def query_maps_numpy(
    Ms: Sequence[FloatArray],
    widths: Sequence[FloatArray],
    n_checks: IntArray,
    order: IntArray,
    n_order: int,
    theta_aug: FloatArray,
    u_out: FloatArray,
    u_min: FloatArray,
    u_max: FloatArray,
) -> int:
    """The reference scan (and the fallback without numba)."""
    for k, i in enumerate(order[:n_order]):
        if apply_map_numpy(Ms[i], widths[i], theta_aug, int(n_checks[i]), u_out, u_min, u_max):
            return k
    return -1


def _query_maps_jit(
    Ms: Sequence[FloatArray],
    widths: Sequence[FloatArray],
    n_checks: IntArray,
    order: IntArray,
    n_order: int,
    theta_aug: FloatArray,
    u_out: FloatArray,
    u_min: FloatArray,
    u_max: FloatArray,
) -> int:
    """:func:`query_maps_numpy` compiled whole, over the compiled check ``_apply_jit`` (a
    module global, so that numba's disk cache keys it: a closure over it missed the cache
    and recompiled in every process)."""
    for k in range(min(n_order, order.shape[0])):
        i = order[k]
        if _apply_jit(Ms[i], widths[i], theta_aug, n_checks[i], u_out, u_min, u_max):
            return k
    return -1


_apply_jit: Any = None


def _compile() -> tuple[ApplyMap, QueryMaps] | None:
    if not jit.enabled():  # the numpy twins (a cold start, see common.jit)
        return None
    try:
        import numba  # noqa: F401  (compiled below, by jit.njit_cached)
    except ImportError:  # numba is a dependency; keep working without it, only slower
        return None

    def apply_map_numba(
        M: FloatArray,
        width: FloatArray,
        theta_aug: FloatArray,
        n_check: int,
        u_out: FloatArray,
        u_min: FloatArray,
        u_max: FloatArray,
    ) -> bool:
        rows, cols = M.shape
        for i in range(n_check):
            s = 0.0
            for j in range(cols):
                s += M[i, j] * theta_aug[j]
            if not (s >= 0.0 and s <= width[i]):
                return False
        for i in range(n_check, rows):
            s = 0.0
            for j in range(cols):
                s += M[i, j] * theta_aug[j]
            k = i - n_check
            u_out[k] = min(max(s, u_min[k]), u_max[k])
        return True

    # reassoc/contract let the dot product vectorise; no nnan/ninf: widths may be +inf.
    # The on-disk cache spares the ~1 s compile on later starts; without a writable cache
    # location numba refuses cache=True, so compile in memory then.
    compiled = jit.njit_cached(apply_map_numba, nogil=True, fastmath={"reassoc", "contract"})
    global _apply_jit
    _apply_jit = compiled
    query = jit.njit_cached(_query_maps_jit, nogil=True)
    return cast(ApplyMap, compiled), cast(QueryMaps, query)


MapLists = tuple[MutableSequence[Any], MutableSequence[Any]]


def _store_numpy(Ms: MutableSequence[Any], widths: MutableSequence[Any], slot: int,
                 M: FloatArray, width: FloatArray) -> None:
    if slot == len(Ms):
        Ms.append(M)
        widths.append(width)
    else:
        Ms[slot] = M
        widths[slot] = width


def _compile_lists() -> tuple[Callable[[], MapLists], Callable[..., None]] | None:
    """Numba typed lists made and written only inside cached compiled functions: a typed
    list's own methods, called from Python, compile anew in every process (~1 s, several
    under load), which delayed start-up enough to shift a lockstep flight's handshake."""
    if _NUMBA is None:
        return None
    from numba import types
    from numba.typed import List

    mat, vec = types.float64[:, ::1], types.float64[::1]

    def new_lists() -> MapLists:
        return List.empty_list(mat), List.empty_list(vec)

    made = jit.njit_cached(new_lists)
    stored = jit.njit_cached(cast(Callable[..., None], _store_numpy))
    return made, stored


def new_map_lists() -> MapLists:
    """The containers :func:`query_maps` takes its per-map arrays in (matrices, widths):
    numba typed lists (passed to the compiled scan without conversion) or, without numba,
    Python lists. Write them with :func:`store_map` only."""
    return ([], []) if _LISTS is None else _LISTS[0]()


def store_map(lists: MapLists, slot: int, M: FloatArray, width: FloatArray) -> None:
    """Put a map's ``M`` (C-contiguous float64, 2-D) and ``width`` in ``slot``: the next
    slot (appended) or one already there (replaced)."""
    if _LISTS is None:
        _store_numpy(lists[0], lists[1], slot, M, width)
    else:
        _LISTS[1](lists[0], lists[1], slot, M, width)


_warm = False


def warm_up() -> None:
    """Compile (or load from the cache) the scan and the typed list's methods now: the first
    miss of a flight must not pay for it, nor the miss worker's first solve, which a lockstep
    tick waits for (docs/DESIGN.md, timing on a companion computer). Once per process."""
    global _warm
    if _warm:
        return
    _warm = True
    lists = new_map_lists()
    for slot in (0, 1, 1):  # append, append, then the slot reuse path
        store_map(lists, slot, np.zeros((2, 2)), np.full(1, np.inf))
    Ms, widths = lists
    u = np.empty(1)
    n_checks = np.ones(2, dtype=np.int64)
    query_maps(Ms, widths, n_checks, np.arange(2, dtype=np.int64), 2, np.ones(2), u,
               np.full(1, -1.0), np.full(1, 1.0))


_NUMBA = _compile()
apply_map: ApplyMap = _NUMBA[0] if _NUMBA is not None else apply_map_numpy
query_maps: QueryMaps = _NUMBA[1] if _NUMBA is not None else query_maps_numpy
_LISTS = _compile_lists()
HAVE_NUMBA = _NUMBA is not None


# -- the position tick's disturbance plan -------------------------------------------------------


def _disturbance_plan_jit(
    p_hat: FloatArray,
    d_along: FloatArray,
    d_max: float,
    refs: FloatArray,
    alpha: FloatArray,
    one_minus_alpha: FloatArray,
    h: float,
    u_p: FloatArray,
    refs_out: FloatArray,
    d_hat: FloatArray,
) -> None:
    """The position tick's nominal inputs and shifted references from the disturbance
    estimate in one call: :meth:`PositionLoop.position_tick
    <epc_offboard.control.position.PositionLoop.position_tick>`'s numpy code (its twin, about
    25 calls on (N, 3) arrays, each a few cold cache lines in real time; issue 21) with
    numpy's operations in numpy's order, so the bits are the same:

    * ``d_hat`` (3,) = clip(``p_hat``, +-``d_max``);
    * d_var (N + 1, 3) = clip(d_hat + (``d_along``[1:] - ``d_along``[1]), +-d_max) - d_hat;
    * ``u_p`` (N, 3) = feedforward(``refs``) - d_hat - lag_inverse(d_var);
    * ``refs_out`` (N, 9) = ``refs`` - disturbance_drift(d_var) (``h``: the prediction step).

    A clip is numpy's minimum(maximum()): a NaN stays NaN.
    """
    n = refs.shape[0]
    lo, hi = -d_max, d_max
    dv = np.empty((n + 1, 3))
    for i in range(3):
        x = p_hat[i]
        if x < lo:
            x = lo
        if x > hi:
            x = hi
        d_hat[i] = x
        base = d_along[1, i]
        for k in range(n + 1):
            x = d_hat[i] + (d_along[k + 1, i] - base)
            if x < lo:
                x = lo
            if x > hi:
                x = hi
            dv[k, i] = x - d_hat[i]
    c = 0.5 * h * h
    for i in range(3):
        a, oma = alpha[i], one_minus_alpha[i]
        # a_0 extrapolated from the reference's a_1 and a_2 (feedforward)
        a_prev = 2.0 * refs[0, 6 + i] - refs[1, 6 + i] if n >= 2 else refs[0, 6 + i]
        s_v = 0.0
        s_p = 0.0
        for k in range(n):
            a_next = refs[k, 6 + i]
            u_p[k, i] = ((a_next - a * a_prev) / oma - d_hat[i]
                         - (dv[k + 1, i] - a * dv[k, i]) / oma)  # fmt: skip
            a_prev = a_next
            # the drift's cumulative sums start at their first term, as numpy's do
            d = dv[k, i]
            s_v = d if k == 0 else s_v + d
            v = s_v * h
            term = h * (v - h * d) + c * d
            s_p = term if k == 0 else s_p + term
            refs_out[k, i] = refs[k, i] - s_p
            refs_out[k, 3 + i] = refs[k, 3 + i] - v
            refs_out[k, 6 + i] = refs[k, 6 + i] - 0.0


def _compile_plan() -> Callable[..., None] | None:
    """The compiled disturbance plan (None on the numpy twins: the caller's numpy code)."""
    if _NUMBA is None:
        return None
    return jit.njit_cached(cast(Callable[..., None], _disturbance_plan_jit), nogil=True)


disturbance_plan = _compile_plan()
_plan = cast(Callable[..., None], disturbance_plan)  # (called by filtered_plan where compiled)


def _filtered_plan_jit(raw: FloatArray, refs: FloatArray, d_hat: FloatArray, state: FloatArray,
                       consts: FloatArray, u_p: FloatArray, refs_out: FloatArray) -> None:
    """:func:`disturbance_plan` from the LWPR estimator's raw predictions ``raw`` (N + 2, 3)
    at the tick's query points (the velocity now, the variation's origin, the reference's
    velocities), its low-pass filter's ``state`` (3,) stepped here: ``estimate_along``
    (``filter.step(raw[0])``, ``raw - raw[0]``) and the plan in one call, element by
    element in numpy's order (the same bits; issue 21: those numpy calls were a cold tick's
    cache lines). ``consts`` (9,): the lag's alpha (3), 1 - alpha (3), the filter's gain,
    d_max and the prediction step h; ``d_hat`` and the plan's outputs as
    :func:`disturbance_plan` writes them. Seven arrays: a compiled call unboxes each (a few
    us apiece with the caches cold; packing four into a typed list cost more than it
    saved)."""
    gain = consts[6]
    for i in range(state.shape[0]):  # LowPassFilter.step: state += gain * (u - state)
        state[i] = state[i] + gain * (raw[0, i] - state[i])
    d_along = np.empty(raw.shape)
    for k in range(raw.shape[0]):
        for i in range(raw.shape[1]):
            d_along[k, i] = raw[k, i] - raw[0, i]
    _plan(state, d_along, consts[7], refs, consts[0:3], consts[3:6], consts[8], u_p, refs_out,
          d_hat)  # fmt: skip


def _compile_filtered_plan() -> Callable[..., None] | None:
    """The compiled filtered plan (None on the numpy twins: the caller's numpy code)."""
    if _NUMBA is None:
        return None
    return jit.njit_cached(cast(Callable[..., None], _filtered_plan_jit))  # (the GIL kept)


filtered_plan = _compile_filtered_plan()
_filtered = cast(Callable[..., None], filtered_plan)  # (called by lwpr_plan where compiled)


def _lwpr_plan_jit(vel: FloatArray, stages: FloatArray, origin_is_vel: bool, lead_base: int,
                   lead_frac: float, ns: Any, packed: Any, packed_type: Any, z: FloatArray,
                   raw: FloatArray, pos: FloatArray, vel0: FloatArray, achieved: FloatArray,
                   d_last: FloatArray, age_s: float, d_hat: FloatArray, state: FloatArray,
                   consts: FloatArray, u_p: FloatArray, refs: FloatArray, x0: FloatArray,
                   sent: FloatArray, missing: int) -> bool:
    """The position tick's numerics before the EPC step, in one compiled call over the
    tick's preallocated buffers (issue 21: each numpy call and each compiled entry is a
    machinery a cold tick pays for, and each array a compiled call unboxes a few cold cache
    lines). Its stages, in the order the Python code they stand for ran them:

    1. **the reference window**, rows N..2N-1 of ``refs`` (2N, 9), from ``stages`` (M + 1,
       9) (``DeadTimePredictor.window``): rows ``lead_base + 1 + k`` (the last row held past
       the end), and ``lead_frac`` of the way to the next when it is not 0 (``lo + frac
       (hi - lo)`` as it computes it: the same bits);
    2. **the query points** ``z`` (N + 2, 3): ``vel`` (the velocity the disturbance is looked
       up at), the variation's origin (``stages``' row 0 velocity, or ``vel`` when
       ``origin_is_vel``), the window's velocities;
    3. **LWPR's predictions** there into ``raw`` (zeroed first: the columns no model writes
       stay 0), :func:`~epc_offboard.control.lwpr_kernels.predict_groups_packed` on ``ns``,
       ``packed`` and ``packed_type`` (``ModelGroup.predict_args``);
    4. **the filter's step and the plan**, :func:`filtered_plan` on the window (``d_hat``,
       ``state``, ``consts``' first 9, ``u_p`` as it writes them; its references into rows
       0..N-1 of ``refs``);
    5. **x0**, ``x0[0:9]`` = [p, v, a]: ``pos`` and ``vel0`` carried ``age_s`` on by the
       model's acceleration ``achieved + d_last`` (when ``age_s`` > 0), then ``achieved``;
    6. **the command dead time** (``DeadTimePredictor.ahead``, when ``sent`` has rows):
       ``x0 <- Phi x0 + W sent + Wd d_hat``, the oldest ``missing`` rows of ``sent`` taken
       as x0's acceleration (not flown by us); ``consts[9:]`` = [Phi (9x9), W (9 x 3n),
       Wd (9x3), E (9x3)] row-major (:func:`dead_time_constants`);
    7. **the perturbation** the QP's model carries, ``E d_hat``, into ``x0[9:18]``.

    Stages 1-5 are the same bits as the Python code; 6 and 7 sum each row's products in
    order where numpy's matrix-vector products are BLAS's (blocked, by machine): they
    differ in the last bits (``tests/test_tick_cost.py`` holds them to 1e-12 relative).

    False (a query point or a normalised input not finite): only the window, ``z`` and
    ``raw`` were written; the caller takes the models one by one."""
    n = refs.shape[0] // 2
    window = refs[n:]
    last = stages.shape[0] - 1
    for k in range(n):  # 1. the reference window
        lo = min(lead_base + 1 + k, last)
        if lead_frac < 1e-9:
            for i in range(9):
                window[k, i] = stages[lo, i]
        else:
            hi = min(lo + 1, last)
            for i in range(9):
                window[k, i] = (stages[hi, i] - stages[lo, i]) * lead_frac + stages[lo, i]
    for i in range(3):  # 2. the query points
        z[0, i] = vel[i]
        z[1, i] = vel[i] if origin_is_vel else stages[0, 3 + i]
    for k in range(n):
        for i in range(3):
            z[k + 2, i] = window[k, 3 + i]
    for k in range(raw.shape[0]):  # 3. LWPR's predictions
        for i in range(raw.shape[1]):
            raw[k, i] = 0.0
    if not _predict_packed(z, raw, ns, packed, packed_type):
        return False
    _filtered(raw, window, d_hat, state, consts, u_p, refs[:n])  # 4. the filter, the plan
    if age_s > 0.0:  # 5. x0 carried over the sample's age
        c = 0.5 * age_s * age_s
        for i in range(3):
            a = achieved[i] + d_last[i]
            x0[i] = pos[i] + c * a
            x0[3 + i] = vel0[i] + a * age_s
    else:
        for i in range(3):
            x0[i] = pos[i]
            x0[3 + i] = vel0[i]
    for i in range(3):
        x0[6 + i] = achieved[i]
    steps = sent.shape[0]
    phi0 = 9  # consts: the plan's 9, Phi (81), W (27 steps), Wd (27), E (27)
    w0 = phi0 + 81
    wd0 = w0 + 27 * steps
    e0 = wd0 + 27
    if steps:  # 6. the command dead time
        ahead = np.empty(9)
        for r in range(9):
            s_phi = 0.0
            for j in range(9):
                s_phi += consts[phi0 + r * 9 + j] * x0[j]
            s_w = 0.0
            for j in range(steps):
                for i in range(3):
                    u = x0[6 + i] if j < missing else sent[j, i]
                    s_w += consts[w0 + r * 3 * steps + 3 * j + i] * u
            s_d = 0.0
            for i in range(3):
                s_d += consts[wd0 + r * 3 + i] * d_hat[i]
            ahead[r] = s_phi + s_w + s_d
        for r in range(9):
            x0[r] = ahead[r]
    for r in range(9):  # 7. the perturbation
        s_e = 0.0
        for i in range(3):
            s_e += consts[e0 + r * 3 + i] * d_hat[i]
        x0[9 + r] = s_e
    return True


def dead_time_constants(plan: FloatArray, phi: FloatArray, w: FloatArray, wd: FloatArray,
                        e_dist: FloatArray) -> FloatArray:
    """:func:`lwpr_plan`'s ``consts``: the plan's (9,), the dead time's matrices
    (``DeadTimePredictor.matrices``) and the disturbance's input ``e_dist`` (9, 3), flat,
    row-major, contiguous."""
    parts = [np.ravel(a).astype(np.float64) for a in (plan, phi, w, wd, e_dist)]
    return np.ascontiguousarray(np.concatenate(parts))


def _compile_lwpr_plan() -> Callable[..., bool] | None:
    """The compiled LWPR query and plan (None on the numpy twins: the caller's code)."""
    if _NUMBA is None or filtered_plan is None:
        return None
    from epc_offboard.control import lwpr_kernels

    if not lwpr_kernels.HAVE_NUMBA:
        return None
    global _predict_packed
    _predict_packed = lwpr_kernels.predict_groups_packed
    return jit.njit_cached(cast(Callable[..., bool], _lwpr_plan_jit))  # (the GIL kept)


_predict_packed: Any = None
lwpr_plan = _compile_lwpr_plan()


# -- the position tick's tilt limit -------------------------------------------------------------


def _tilt_reach_jit(
    acc: FloatArray,
    u_min: FloatArray,
    u_max: FloatArray,
    P: FloatArray,
    p: FloatArray,
    out: FloatArray,
) -> float:
    """:func:`~epc_offboard.control.models.limit_tilt`'s box clip (numpy's
    minimum(maximum()), the same bits: a NaN stays NaN) written to ``out``, and the largest
    of the polygon's ratios of horizontal reach to slack at it (NaN if any is). Its
    matrix-vector product is BLAS's there, whose rounding (fused multiply-adds, or not, by
    machine) this does not follow: the caller takes ``out`` as the limit's answer only when
    the ratio is clearly below 1 (no horizontal scaling, so no rounding of it matters), and
    asks the numpy function otherwise."""
    for i in range(3):
        x = acc[i]
        if x < u_min[i]:
            x = u_min[i]
        if x > u_max[i]:
            x = u_max[i]
        out[i] = x
    worst: float = -np.inf
    for j in range(P.shape[0]):
        r = float((P[j, 0] * out[0] + P[j, 1] * out[1]) / (p[j] - P[j, 2] * out[2]))
        if r != r:
            return r
        if r > worst:
            worst = r
    return worst


def _compile_tilt() -> Callable[..., float] | None:
    """The compiled tilt check (None on the numpy twins: the caller's numpy function)."""
    if _NUMBA is None:
        return None
    # holding the interpreter lock: a kernel of a microsecond that released it would only
    # let another thread take it, and the loop wait for it back (up to a switch interval)
    return jit.njit_cached(cast(Callable[..., float], _tilt_reach_jit))


tilt_reach = _compile_tilt()


# -- the EPC step's parameter vector ------------------------------------------------------------


def _stack_theta_jit(
    x0: FloatArray,
    refs: FloatArray,
    u_p: FloatArray,
    c: FloatArray,
    perturbation: FloatArray,
    theta_aug: FloatArray,
    cols: IntArray,
    theta_cols: FloatArray,
) -> bool:
    """:meth:`MpcProblem.theta <epc_offboard.control.qp.MpcProblem.theta>` with a
    perturbation and per-stage nominal inputs, written into ``theta_aug`` ([θ; 1]), and its
    columns ``cols`` (what the library's maps read) into ``theta_cols``: one call instead of
    a dozen numpy calls and a gather (issue 21), the same bits (copies, and ``c + p^``
    element by element). False, nothing written: the shapes do not fit ``theta_aug``."""
    nx, n, nu = x0.shape[0], refs.shape[0], u_p.shape[1]
    if (refs.shape[1] != nx or u_p.shape[0] != n or c.shape[0] != nx
            or perturbation.shape[0] != nx or theta_aug.shape[0] != nx + n * nx + nx + n * nu + 1
            or theta_cols.shape[0] != cols.shape[0]):  # fmt: skip
        return False
    for i in range(nx):
        theta_aug[i] = x0[i]
    k = nx
    for s in range(n):
        for i in range(nx):
            theta_aug[k] = refs[s, i]
            k += 1
    for i in range(nx):
        theta_aug[k] = c[i] + perturbation[i]
        k += 1
    for s in range(n):
        for i in range(nu):
            theta_aug[k] = u_p[s, i]
            k += 1
    for j in range(cols.shape[0]):
        theta_cols[j] = theta_aug[cols[j]]
    return True


def _compile_theta() -> Callable[..., bool] | None:
    """The compiled θ stack (None on the numpy twins: ``MpcProblem.theta``)."""
    if _NUMBA is None:
        return None
    return jit.njit_cached(cast(Callable[..., bool], _stack_theta_jit))  # (the GIL kept: above)


stack_theta = _compile_theta()
_stack = cast(Callable[..., bool], stack_theta)  # (called by theta_check where compiled)



# -- θ and the last controller's check in one call ------------------------------------------


def _theta_check_jit(x0: FloatArray, refs: FloatArray, u_p: FloatArray, c: FloatArray,
                     perturbation: FloatArray, theta_aug: FloatArray, cols: IntArray,
                     theta_cols: FloatArray, M: FloatArray, width: FloatArray, n_check: int,
                     u_out: FloatArray, u_min: FloatArray, u_max: FloatArray) -> int:
    """:func:`stack_theta`, then the last controller's KKT check at its columns
    (:func:`apply_map`, the same compiled check: the same bits) in one compiled call: the
    position tick's EPC hit path entered once instead of twice (each entry is a machinery
    a cold tick pays for; issue 21). -1: the shapes do not fit, nothing written; 0: θ
    stacked, the check failed or was not asked (``n_check`` < 0: no last controller); 1: θ
    stacked and the check passed, its first input written to ``u_out``."""
    if not _stack(x0, refs, u_p, c, perturbation, theta_aug, cols, theta_cols):
        return -1
    if n_check < 0:
        return 0
    if _apply_jit(M, width, theta_cols, n_check, u_out, u_min, u_max):
        return 1
    return 0


def _compile_theta_check() -> Callable[..., int] | None:
    """The compiled θ stack and check (None on the numpy twins)."""
    if _NUMBA is None or stack_theta is None:
        return None
    return jit.njit_cached(cast(Callable[..., int], _theta_check_jit))  # (the GIL kept: above)


theta_check = _compile_theta_check()


# -- the position tick's numerics up to the EPC query in one call -----------------------------


def _plan_step_jit(vel: FloatArray, stages: FloatArray, origin_is_vel: bool, lead_base: int,
                   lead_frac: float, ns: Any, packed: Any, packed_type: Any, z: FloatArray,
                   raw: FloatArray, pos: FloatArray, vel0: FloatArray, achieved: FloatArray,
                   d_last: FloatArray, age_s: float, d_hat: FloatArray, state: FloatArray,
                   consts: FloatArray, u_p: FloatArray, refs: FloatArray, x0: FloatArray,
                   sent: FloatArray, missing: int, c: FloatArray, theta_aug: FloatArray,
                   cols: IntArray, theta_cols: FloatArray, M: FloatArray, width: FloatArray,
                   n_check: int, u_out: FloatArray, u_min: FloatArray,
                   u_max: FloatArray) -> int:
    """:func:`lwpr_plan` (its seven stages, on its first 23 arguments), then
    :func:`theta_check` on what it wrote (8. **θ**, stacked from ``x0[0:9]``, the plan's
    references ``refs[:N]``, ``u_p`` and the model's offset ``c`` plus the perturbation
    ``x0[9:18]``; 9. **the last controller's KKT check** at θ's columns, its input into
    ``u_out``), in one compiled call: the position tick's numerics up to the library's
    query entered once instead of twice (issue 21: each compiled entry is a machinery a
    cold tick pays for). The same compiled functions in the same order: the same bits as
    the two calls.

    -2: the plan was not made (:func:`lwpr_plan`'s False: only the window, ``z`` and
    ``raw`` written; θ not stacked); else :func:`theta_check`'s answer (-1: θ's shapes do
    not fit, nothing of θ written; 0: θ stacked, the check failed or was not asked; 1: it
    passed)."""
    if not _lwpr(vel, stages, origin_is_vel, lead_base, lead_frac, ns, packed, packed_type, z,
                 raw, pos, vel0, achieved, d_last, age_s, d_hat, state, consts, u_p, refs, x0,
                 sent, missing):
        return -2
    n = refs.shape[0] // 2
    return _check(x0[:9], refs[:n], u_p, c, x0[9:], theta_aug, cols, theta_cols, M, width,
                  n_check, u_out, u_min, u_max)


def _compile_plan_step() -> Callable[..., int] | None:
    """The compiled plan and θ with the check (None where either is not compiled)."""
    if lwpr_plan is None or theta_check is None:
        return None
    return jit.njit_cached(cast(Callable[..., int], _plan_step_jit))  # (the GIL kept: above)


_lwpr = cast(Callable[..., bool], lwpr_plan)  # (called by plan_step where compiled)
_check = cast(Callable[..., int], theta_check)
plan_step = _compile_plan_step()
