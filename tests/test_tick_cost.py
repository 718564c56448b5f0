"""What a position step costs, counted rather than timed (a timed test fails on a busy
machine; a count does not): the Python-level calls of one tick of the position loop and of
its flight-log row, and the log's writes per row.

Issue 21: the real-time tick took 0.7-1.0 ms of CPU where 300 us was the target, all of it
work (the tick's thread was on the CPU for its whole wall time), spread over hundreds of
Python-level calls on tiny arrays: the estimator's window rebuilt as objects and lists every
tick, numpy's wrappers (``np.clip``, ``np.linalg.norm``, ``np.vstack``) on (3,) vectors, the
same Euler angles and thrust axis computed three times, a flight-log row packed from numpy
scalars and sent in two writes. These bounds fail if that cost comes back.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from epc_offboard.common import frames
from epc_offboard.common.logsetup import LogConfig
from epc_offboard.control.cascade import Cascade, compiled_signatures
from epc_offboard.control.models import accel_to_attitude
from epc_offboard.control.perturbation import LwprPerturbation
from epc_offboard.control.trajectories import Trajectory, TrajectoryConfig
from epc_offboard.control.types import VehicleState
from epc_offboard.service.config import load_service_config
from epc_offboard.service.flightlog import pack_row
from epc_offboard.service.logwriter import LogWriter

_CONFIG = Path(__file__).resolve().parent.parent / "config" / "sitl.toml"
_DT_S = 0.01  # the position loop's period

# Python-level calls (functions and methods written in Python, numpy's wrappers included)
# and calls into C (builtins, numpy's ufuncs and methods) per tick: the state and reference
# this test builds, the tick (estimator and EPC query included) and its log row. Before
# (issue 21's measurements): 141 and 212; then 84 and 140; then 69 and 128 (the three LWPR
# models learn and predict in one compiled call each, through its entry point; the
# reference window's indices cached), 75 and 130.5 on main 903bae9; then 66-68 and 125.5 (the
# disturbance plan, ~25 numpy calls, in one compiled call); now 67 and 121.5 (the tilt limit
# and θ's stack each in one compiled call); then 67 and 121.5 on main c8cc5a5; now 56 and
# 118.5 (LWPR's filter step and variation in the plan's compiled call, the attitude
# target's quaternion from its floats, the LWPR group's field counts read in C); then 54
# and 108.5 on main e4a2479 (55 and 112.5 with PX4 quaternion's dead time); now 52.5 and
# 108.5 (109.5): the reference window, the dead time's carry and E d_hat in the compiled
# plan; then 53.5 and 108.5 (109.5) on main 06044f0; now 53.5 and 106.5 (107.5): θ and
# the EPC's check in the plan's compiled call (kernels.plan_step; the controller's
# check_args and checked in Python where its step and theta_compiled were). The bounds
# leave room for a small change, not for the old cost (they fail on the code before).
MAX_PYTHON_CALLS = 56
MAX_C_CALLS = 114


def _state(
    t_s: float, pos: np.ndarray, vel: np.ndarray, position_age_s: float,
    acc: np.ndarray | None = None,
) -> VehicleState:
    # tilted for the acceleration it flies (the reference's): at a fixed attitude the
    # estimator learnt the whole reference acceleration as a disturbance of the velocity,
    # which the model now carries along the horizon (metres of drift no flight meets)
    att = accel_to_attitude(np.zeros(3) if acc is None else acc, 0.0, 0.5)
    return VehicleState(
        time_s=t_s,
        pos_ned_m=pos,
        vel_ned_m_s=vel,
        q_ned_frd=frames.euler_to_quat(att.roll_rad + 0.02, att.pitch_rad - 0.03, 0.0),
        rate_frd_rad_s=np.zeros(3),
        position_age_s=position_age_s,
        attitude_age_s=0.0,
    )


def _count_calls(fn: Any, runs: int) -> tuple[float, float]:
    """Median Python-level and C calls of ``fn(k)`` over ``runs`` calls."""
    python_calls: list[int] = []
    c_calls: list[int] = []
    for k in range(runs):
        counts: Counter[str] = Counter()

        def profile(frame: Any, event: str, arg: Any, counts: Counter[str] = counts) -> None:
            counts[event] += 1

        sys.setprofile(profile)
        try:
            fn(k)
        finally:
            sys.setprofile(None)
        python_calls.append(counts["call"])
        c_calls.append(counts["c_call"])
    return float(np.median(python_calls)), float(np.median(c_calls))


def _figure8_ticks() -> tuple[Cascade, Any]:
    """A warmed-up cascade and ``tick(k)``: the figure-8's tick k in offboard (the
    estimator learning, a new position sample every other tick as at 50 Hz), with its
    flight-log row packed."""
    cfg = load_service_config(_CONFIG)
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S,
                      learn_on_miss=True, airframe=cfg.vehicle)  # fmt: skip
    cascade.warm_up()
    loop = cascade.position
    traj = Trajectory(TrajectoryConfig(shape="figure8", ramp_s=1.0, period_s=8.0),
                      np.array([0.0, 0.0, -2.5]))  # fmt: skip

    def tick(k: int) -> None:
        state, reference = _figure8_inputs(traj, loop, k)
        out = cascade.position_tick(state, reference, learn=True)
        pack_row(state.time_s, "offboard", state, reference, out)

    return cascade, tick


def _figure8_inputs(traj: Trajectory, loop: Any, k: int,
                    steps: int | None = None) -> tuple[VehicleState, Any]:
    """The figure-8's tick k: the state (its position sample 0 or 10 ms old, a new one every
    other tick as at 50 Hz) and the reference over ``steps`` stages (unset: the horizon)."""
    t_s = 1.0 + k * _DT_S
    now = traj.sample(t_s - (k % 2) * _DT_S)
    state = _state(t_s, now.pos_ned_m + 0.01, now.vel_ned_m_s * 0.98, (k % 2) * _DT_S,
                   now.acc_ned_m_s2)  # fmt: skip
    return state, traj.reference(t_s, loop.config.dt_s, steps or loop.config.horizon, 0.0)


def test_a_position_tick_makes_few_python_calls():
    """A figure-8 tick in offboard (the EPC library warm), with its flight-log row packed."""
    cascade, tick = _figure8_ticks()
    warm_signatures = compiled_signatures()
    for k in range(400):  # the library learns the figure-8's controllers: then hits
        tick(k)
    python_calls, c_calls = _count_calls(lambda k: tick(400 + k), 200)
    assert cascade.library_stats()["position"]["hits"] > 0
    # the warm-up compiled every kernel the ticks call (the estimator's learning step in
    # one call too): nothing compiles on the loop
    assert compiled_signatures() == warm_signatures
    assert python_calls <= MAX_PYTHON_CALLS, f"{python_calls} Python-level calls a tick"
    assert c_calls <= MAX_C_CALLS, f"{c_calls} C calls a tick"


def _arrays_in(value: Any) -> int:
    if isinstance(value, np.ndarray):
        return 1
    if isinstance(value, tuple):
        return sum(_arrays_in(v) for v in value)
    return 0


def test_the_estimators_kernels_unbox_few_arrays_a_call():
    """A compiled call unboxes every array of its arguments, each a cold cache line or more
    10 ms after the last tick: the estimator's update took its models' field stores as ~110
    arrays (5 us a call warm, 48 us with the caches cold, for a few us of work; issue 21),
    its prediction ~40. Packed into one object (``lwpr_kernels.packed``), a few each."""
    cascade, tick = _figure8_ticks()
    for k in range(50):  # the models have fields: both kernels run
        tick(k)
    loop = cascade.position
    estimator = loop.estimator
    assert isinstance(estimator, LwprPerturbation)
    group = estimator._model_group()
    fused = loop._lwpr_plan
    fused_arrays: list[int] = []
    if fused is not None:
        # the tick's query runs the prediction inside the compiled plan (kernels.lwpr_plan,
        # with θ and the EPC's check: kernels.plan_step): the models' fields packed there
        # too; then the group's own kernel, the plan off
        attr = "_lwpr_plan" if loop._plan_step is None else "_plan_step"
        kernel = getattr(loop, attr)

        def counting_plan(*args: Any, _kernel: Any = kernel) -> Any:
            fused_arrays.append(_arrays_in(args))
            return _kernel(*args)

        setattr(loop, attr, counting_plan)
        for k in range(50, 55):
            tick(k)
        # its own arrays (the state, points, filter, plan, x0 and the dead time's commands:
        # 15; the window shares the plan's buffer, the perturbation x0's, the dead time's
        # matrices the plan's constants), not the models' ~40; with θ and the check 9 more
        # (the offset, θ, its columns and their buffer, the map, its widths, the input and
        # its bounds: x0, the references, u_p and the perturbation are the plan's)
        assert fused_arrays
        assert max(fused_arrays) <= (15 if attr == "_lwpr_plan" else 24), fused_arrays
        loop._lwpr_plan = loop._plan_step = None
        for k in range(55, 57):
            tick(k)
    arrays: dict[str, list[int]] = {"update": [], "predict": []}
    for name, attr in (("update", "_update_kernel"), ("predict", "_kernel")):
        kernel = getattr(group, attr)
        assert kernel is not None, f"the {name} kernel never ran"

        def counting(*args: Any, _kernel: Any = kernel, _seen: list[int] = arrays[name]) -> Any:
            _seen.append(_arrays_in(args))
            return _kernel(*args)

        setattr(group, attr, counting)
    for k in range(60, 70):
        tick(k)
    assert arrays["update"]
    assert arrays["predict"]
    # the sample (z, p) or the points and their output (zs, raw): 2 arrays, the rest packed
    assert max(arrays["update"]) <= 2, arrays["update"]
    assert max(arrays["predict"]) <= 2, arrays["predict"]


def test_flight_log_rows_share_writes(tmp_path, monkeypatch):
    """Each write to the log writer's pipe woke its process (7 us of the tick's CPU): rows
    go four to a write, with the tick's tlog frames."""
    counters: Counter[str] = Counter()
    logs = LogWriter(str(tmp_path / "flight.csv"), str(tmp_path / "s.tlog"), LogConfig(),
                     counters)  # fmt: skip
    logs.start()
    writes: list[int] = []
    real_write = os.write

    def counting_write(fd: int, data: bytes) -> int:
        writes.append(len(data))
        return real_write(fd, data)

    cascade = Cascade(*(lambda c: (c.position, c.attitude, c.estimator))(
        load_service_config(_CONFIG)), _DT_S)  # fmt: skip
    state = _state(1.0, np.zeros(3), np.zeros(3), 0.0)
    out = cascade.hover(state)
    ref = cascade.position.hold(np.zeros(3))
    try:
        monkeypatch.setattr(os, "write", counting_write)
        for k in range(100):
            assert logs.tlog is not None
            logs.tlog.write(bytes([0xFD, 9, 0, 0, k]), 1.7e9 + k)
            logs.flight_row(pack_row(1.0 + 0.01 * k, "offboard", state, ref, out))
        monkeypatch.undo()
    finally:
        logs.close()
    assert len(writes) <= 26, f"{len(writes)} writes for 100 rows"
    rows = (tmp_path / "flight.csv").read_text().splitlines()
    assert len(rows) == 101  # the header and every row
    assert counters["log_records_dropped"] == 0


def test_the_scalar_paths_are_numpys_to_the_last_bit():
    """The tick's float arithmetic replaced numpy calls only where it gives numpy's numbers
    exactly (the lockstep flights are bit-identical): the pairwise sum of a 1-D mean, the
    norm as the square root of a dot product."""
    from epc_offboard.control.position import _pairwise_sum

    rng = np.random.default_rng(7)
    for n in [*range(1, 70), 127, 128, 129, 300]:
        for scale in (1e-3, 1.0, 1e3):
            values = rng.normal(size=n) * scale
            assert _pairwise_sum(values.tolist()) == values.sum()
            assert _pairwise_sum(values.tolist()) / n == values.mean()
    for _ in range(2000):
        v = rng.normal(size=int(rng.integers(3, 5))) * rng.choice([1e-3, 1.0, 1e3])
        assert frames.vector_norm(v) == float(np.linalg.norm(v))


def test_the_compiled_disturbance_plan_is_the_numpy_codes_to_the_last_bit():
    """The position tick's disturbance plan (nominal inputs and shifted references) in one
    compiled call gives the numpy code's bits (kept as its twin), clipping included: the
    lockstep flights stay bit-identical."""
    from epc_offboard.control.kernels import disturbance_plan

    if disturbance_plan is None:
        pytest.skip("numba is not in use: the numpy code is all there is")
    cfg = load_service_config(_CONFIG)
    loop = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S).position
    n, h = loop.config.horizon, loop.config.dt_s
    d_max = loop._d_max
    rng = np.random.default_rng(3)
    for case in range(300):
        scale = (0.1, 1.0, 3.0 * d_max)[case % 3]  # the last one clips
        p_hat = rng.normal(size=3) * scale
        d_along = rng.normal(size=(n + 2, 3)) * scale
        refs = rng.normal(size=(n, 9)) * (1.0, 10.0, 100.0)[case % 3]
        # the twin, as position_tick writes it
        d_var = d_along[1:] - d_along[1]
        d_hat = np.minimum(np.maximum(p_hat, -d_max), d_max)
        d_var = np.minimum(np.maximum(d_hat + d_var, -d_max), d_max) - d_hat
        u_p = loop.feedforward(refs) - d_hat - loop.lag_inverse(d_var)
        refs_twin = refs - loop.disturbance_drift(d_var)
        out_u_p, out_refs, out_d_hat = np.empty((n, 3)), np.empty((n, 9)), np.empty(3)
        disturbance_plan(p_hat, d_along, d_max, refs, loop.acc_alpha, loop._one_minus_alpha,
                         h, out_u_p, out_refs, out_d_hat)  # fmt: skip
        for twin, compiled in ((d_hat, out_d_hat), (u_p, out_u_p), (refs_twin, out_refs)):
            assert np.array_equal(twin.view(np.uint64), compiled.view(np.uint64)), case


def test_the_filtered_plan_is_estimate_along_and_the_plan_to_the_last_bit():
    """With LWPR (no residual observer) the tick hands the estimator's raw predictions to
    one compiled call that steps its low-pass filter, takes the variation and makes the
    plan (``kernels.filtered_plan``): the bits of ``estimate_along`` (``LowPassFilter.step``,
    ``raw - raw[0]``) and of the plan's numpy twin, the filter's state included, clipping
    included; the lockstep flights stay bit-identical."""
    from epc_offboard.control.perturbation import LowPassFilter

    cfg = load_service_config(_CONFIG)
    loop = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S).position
    plan = loop._filtered_plan()
    if plan is None:
        pytest.skip("numba is not in use: the numpy code is all there is")
    kernel, state, consts = plan
    estimator = loop.estimator
    assert isinstance(estimator, LwprPerturbation)
    assert state is estimator.filter.state
    filt = estimator.filter
    n, d_max = loop.config.horizon, loop._d_max
    rng = np.random.default_rng(13)
    for case in range(300):
        scale = (0.1, 1.0, 3.0 * d_max)[case % 3]  # the last one clips
        raw = rng.normal(size=(n + 2, 3)) * scale
        refs = rng.normal(size=(n, 9)) * (1.0, 10.0, 100.0)[case % 3]
        # the twin: estimate_along's filter step and variation, then the plan's numpy code
        twin = LowPassFilter(3, filt.cutoff_hz, filt.dt_s)
        twin.state[:] = filt.state
        p_hat, d_along = twin.step(raw[0]), raw - raw[0]
        d_var = d_along[1:] - d_along[1]
        d_hat = np.minimum(np.maximum(p_hat, -d_max), d_max)
        d_var = np.minimum(np.maximum(d_hat + d_var, -d_max), d_max) - d_hat
        u_p = loop.feedforward(refs) - d_hat - loop.lag_inverse(d_var)
        refs_twin = refs - loop.disturbance_drift(d_var)
        out_d_hat = np.empty(3)
        kernel(raw, refs, out_d_hat, state, consts, loop._u_p, loop._refs)
        for want, got in ((twin.state, filt.state), (d_hat, out_d_hat), (u_p, loop._u_p),
                          (refs_twin, loop._refs)):  # fmt: skip
            assert np.array_equal(want.view(np.uint64), got.view(np.uint64)), case


def test_the_tick_takes_the_general_way_where_the_filtered_plan_does_not_fit():
    """The filtered plan is LWPR's alone: a Kalman estimator, LWPR with the residual
    observer (its estimate joins between the filter and the plan) or a wrapped estimator
    take ``estimate_along`` and the plan as before."""
    from dataclasses import replace

    cfg = load_service_config(_CONFIG)
    if Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S).position._filtered_plan() is None:
        pytest.skip("numba is not in use: the numpy code is all there is")
    kf = replace(cfg.estimator, kind="kf")
    residual = replace(cfg.estimator, lwpr=replace(cfg.estimator.lwpr, residual_kf=True))
    for estimator in (kf, residual):
        loop = Cascade(cfg.position, cfg.attitude, estimator, _DT_S).position
        assert loop._filtered_plan() is None
    loop = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S).position
    assert loop._filtered_plan() is not None
    loop.estimator = object()  # type: ignore[assignment]
    assert loop._filtered_plan() is None


def _quat_normalize_array(q: Any) -> np.ndarray:
    """``frames.quat_normalize`` as it was written on arrays (before stop 35): the oracle of
    its float form."""
    qa = np.asarray(q, dtype=np.float64)
    n = frames.vector_norm(qa)
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"cannot normalise quaternion {qa!r}")
    qa = qa / n
    return -qa if qa[0] < 0.0 else qa


def test_quat_normalize_is_its_array_forms_to_the_last_bit():
    """``quat_normalize`` divides four floats, not an array (no temporaries, no Python-level
    call; ``euler_to_quat`` calls it on the position tick, the SITL every step): the array
    form's bits, the sign and signed zeros included, and the same refusals."""
    rng = np.random.default_rng(23)
    for case in range(20000):
        q = rng.normal(size=4) * (1e-5, 0.3, 1.0, 1e3)[case % 4]
        if case % 7 == 0:
            q[case % 4] = 0.0
        if case % 11 == 0:
            q[0] = -0.0 if case % 22 else 0.0
        for given in (q, q.tolist()):
            want, got = _quat_normalize_array(given), frames.quat_normalize(given)
            assert got.dtype == np.float64
            assert got.shape == (4,)
            assert np.array_equal(want.view(np.uint64), got.view(np.uint64)), case
    for bad in ([0.0, 0.0, 0.0, 0.0], [math.nan, 0.0, 0.0, 1.0], [math.inf, 0.0, 0.0, 0.0],
                [1e-13, 0.0, 0.0, 0.0], [1e200, 1e200, 0.0, 0.0]):  # fmt: skip
        with pytest.raises(ValueError, match="quaternion"):
            _quat_normalize_array(bad)
        with pytest.raises(ValueError, match="quaternion"):
            frames.quat_normalize(bad)
    with pytest.raises(ValueError, match="quaternion"):
        frames.quat_normalize([1.0, 0.0, 0.0])


def test_the_quaternion_from_euler_angles_is_the_array_forms_to_the_last_bit():
    """``euler_to_quat`` normalises through ``quat_normalize``'s float form: the array
    form's bits, the sign included."""
    rng = np.random.default_rng(17)
    for case in range(20000):
        roll, pitch, yaw = rng.normal(size=3) * (1e-6, 0.1, 1.0, 4.0)[case % 4]
        roll, pitch, yaw = float(roll), float(pitch), float(yaw)
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        want = _quat_normalize_array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                                      cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])
        got = frames.euler_to_quat(roll, pitch, yaw)
        assert np.array_equal(want.view(np.uint64), got.view(np.uint64)), case


def test_the_compiled_tilt_limit_is_limit_tilts_to_the_last_bit():
    """The position tick's tilt limit (twice a tick) in one compiled call where no
    horizontal scaling is near, numpy's function where one is: its bits whatever ``acc``
    (inside, on and beyond the polygon, NaN), so the lockstep flights stay bit-identical."""
    from epc_offboard.control.models import limit_tilt

    cfg = load_service_config(_CONFIG)
    loop = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S).position
    if loop._tilt_reach is None:
        pytest.skip("numba is not in use: the numpy function is all there is")
    rng = np.random.default_rng(5)
    for case in range(20000):
        acc = rng.normal(size=3) * (0.3, 2.0, 6.0, 30.0)[case % 4]
        if case % 97 == 0:
            acc[case % 3] = np.nan
        twin = limit_tilt(acc.copy(), loop.acc_limits)
        out = loop._limit_tilt(acc.copy())
        assert np.array_equal(twin.view(np.uint64), out.view(np.uint64)), (case, acc)
    # both paths ran: the small samples scale nothing (compiled), the large ones do (numpy)
    lim = loop.acc_limits
    out = np.empty(3)
    assert loop._tilt_reach(np.array([0.1, 0.1, 0.0]), lim.u_min, lim.u_max, lim.P, lim.p,
                            out) < 1.0  # fmt: skip
    assert loop._tilt_reach(np.array([30.0, 0.0, 0.0]), lim.u_min, lim.u_max, lim.P, lim.p,
                            out) > 1.0  # fmt: skip


def test_the_compiled_theta_is_the_problems_to_the_last_bit():
    """The EPC step stacks θ (and the columns its maps read) in one compiled call on the
    position tick's path: the bits of ``MpcProblem.theta``, the gather of the maps' columns;
    arguments of another shape go the general way."""
    cfg = load_service_config(_CONFIG)
    controller: Any = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S).position.controller
    problem = controller.problem
    n, nx, nu = problem.horizon, problem.nx, problem.nu
    rng = np.random.default_rng(11)
    for _ in range(200):
        x0, refs = rng.normal(size=nx), rng.normal(size=(n, nx)) * 10.0
        u_p, pert = rng.normal(size=(n, nu)), rng.normal(size=nx)
        controller.step(x0, refs, u_p, perturbation=pert)
        twin = np.append(problem.theta(x0, refs, u_p, perturbation=pert), 1.0)
        assert np.array_equal(controller._theta_aug.view(np.uint64), twin.view(np.uint64))
        assert np.array_equal(controller._theta_cols, twin[controller.builder.geom.cols])
    # a wrong shape is the problem's error, as before (not a write out of bounds)
    with pytest.raises(ValueError, match="refs"):
        controller.step(x0, refs[:-1], u_p, perturbation=pert)


def test_a_map_holds_only_the_columns_some_map_depends_on():
    """The references' accelerations are not weighed (``q_acc`` 0): their 60 columns were
    zeros in every map, read at every hit (520 kB a map, cold each tick in real time). A map
    now holds the columns it can depend on (a map depending on another is refused when
    built: see ``ActiveSetMap``)."""
    cfg = load_service_config(_CONFIG)
    loop = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S).position
    controller: Any = loop.controller
    problem, builder = controller.problem, controller.builder
    assert not any(cfg.position.q_acc)
    assert len(builder.geom.cols) == problem.n_theta + 1 - 3 * problem.horizon
    rng = np.random.default_rng(2)
    built = 0
    for active in [(), *[(int(i),) for i in rng.choice(problem.n_con, 40, replace=False)]]:
        try:
            amap = builder.build(active)
        except ValueError:
            continue
        assert amap.M.shape[1] == problem.n_theta + 1 - 3 * problem.horizon
        assert builder.fits(amap)
        built += 1
    assert built > 10


def test_the_fleet_state_a_save_takes_on_the_loops_thread_is_packed_once(monkeypatch):
    """Every library save (5 s) lists the fleet's received controllers on the loops' thread
    (``FleetSharing.fleet_state_steps``, for a restart). Rebuilt whole each time, the
    backlog's 2,048 controllers took 20-30 ms there: under a fleet's traffic a 20-30 ms
    position-loop gap every 5 s (``bench --attack``'s figure-8, issue 21). Only what arrived
    since the last save may cost calls now (each controller is packed once, the store
    process formats the text); what is saved stays the same."""
    from epc_offboard.fleet.config import SharingConfig
    from epc_offboard.fleet.sharing import FleetSharing

    cfg = load_service_config(_CONFIG)
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, _DT_S)
    sharing = FleetSharing(SharingConfig(enabled=True, vehicle_id="me"),
                           cascade.experience_controllers())  # fmt: skip
    sig = sharing.specs[0].signature
    n_con = sharing.specs[0].n_con
    pairs = [(i, j) for i in range(n_con) for j in range(i + 1, n_con)]

    def received(first: int, n: int) -> str:
        return json.dumps([[list(pairs[k]), f"peer{k % 64}", float(k), k % 7, [list(pairs[k + 1])]]
                           for k in range(first, first + n)])  # fmt: skip

    backlog = cfg.candidates.backlog_size
    assert sharing.restore({f"candidates:{sig}": received(0, backlog)}) == backlog
    # a saver takes it in slices (the loops tick in between), 64 controllers at a time
    steps = list(sharing.fleet_state_steps(64))
    # at most 64 at a time (an origin's 32 here: a part each)
    assert len(steps) >= backlog // 64 + 1
    assert steps[:-1] == [None] * (len(steps) - 1)
    first = sharing.fleet_state()
    # ten more arrive (the oldest leave the bounded backlog); the next save
    sharing.restore({f"candidates:{sig}": received(backlog, 10)})
    calls: Counter[str] = Counter()

    def profile(frame: Any, event: str, arg: Any) -> None:
        calls[event] += 1

    sys.setprofile(profile)
    try:
        *_, taken = sharing.fleet_state_steps()  # what the loops' thread does
    finally:
        sys.setprofile(None)
    # before: 2,134 Python-level calls (an entry built per known controller), now ~100
    # (the ten new ones packed); C calls stay 1-3 per controller (dict look-ups)
    assert calls["call"] <= 300, dict(calls)
    # the same texts (built by the store process): a fresh list of what is known
    assert taken is not None
    second = {k: v if isinstance(v, str) else v.build() for k, v in taken.items()}
    again = json.loads(second[f"candidates:{sig}"])
    assert len(again) == backlog
    assert len(json.loads(first[f"candidates:{sig}"])) == backlog
    assert {tuple(e[0]) for e in again} == {
        e.active_set for e, _s in sharing._libraries[0][1].received()
    }


def test_a_tick_walks_no_candidate_pool_while_no_origin_is_proven():
    """The miss worker's pump asks the pool which maps to build every position tick; with
    nobody's candidates proven (a flood's never are) none is wanted, and a full pool is not
    walked to find that out (64 calls a tick under bench --attack's fleet traffic)."""
    from epc_offboard.control.epc.candidates import CandidatePool

    pool = CandidatePool(64, 16)
    for k in range(200):
        pool.offer((k, k + 1), f"peer{k % 20}")
    assert len(pool) == 64
    python_calls, _c_calls = _count_calls(lambda k: pool.wanted(8), 5)
    assert python_calls <= 2, python_calls
    pool.promoted(next(a for a, _o in pool.items()), "peer19")  # proven: now it walks
    assert pool.wanted(8)


def test_the_stage_tool_times_every_stage_of_the_tick():
    """``python -m epc_offboard.tools.tick_stages`` (issue 21's warm/cold figures): every
    stage it wraps is timed on every tick (no timing is asserted: counts only)."""
    from epc_offboard.tools.tick_stages import format_report, measure

    report = measure(_CONFIG, 6, ("warm", "evict"))
    for mode in ("warm", "evict"):
        stages = report[mode]["stages_us"]
        # the compiled plan with θ and the check (kernels.plan_step), or its parts
        fused = ("plan_step",) if "plan_step" in stages else ("estimate_along", "epc.theta")
        for name in ("position_tick", "reference", "pack_row", "epc.step", "epc.query",
                     "attitude_target", "observe", *fused):
            assert stages[name]["ticks"] == 6, (mode, name)
    assert "position_tick" in format_report(report)


def _accel_to_attitude_array(acc: np.ndarray, yaw_rad: float,
                             hover: float) -> tuple[float, float, float, float]:
    """``models.accel_to_attitude`` as it was written on arrays (before stop 36): the oracle
    of its float form."""
    f = acc - np.array([0.0, 0.0, frames.GRAVITY_M_S2])
    mag = frames.vector_norm(f)
    if mag < 1e-9:
        return 0.0, 0.0, yaw_rad, 0.0
    fx, fy, fz = f.tolist()
    zx, zy, bz = -fx / mag, -fy / mag, -fz / mag
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    bx = cy * zx + sy * zy
    by = -sy * zx + cy * zy
    return (math.atan2(-by, math.hypot(bx, bz)), math.atan2(bx, bz), yaw_rad,
            hover * mag / frames.GRAVITY_M_S2)  # fmt: skip


def test_the_attitude_from_an_acceleration_is_the_array_forms_to_the_last_bit():
    """``accel_to_attitude`` on a (3,) command computes on its floats (no numpy subtraction
    or dot product: a cold tick's machinery, issue 21): the array form's bits, free fall,
    NaN and -0.0 included, so the lockstep flights stay bit-identical."""
    rng = np.random.default_rng(23)
    cases = [np.array([0.0, 0.0, frames.GRAVITY_M_S2]), np.array([-0.0, -0.0, 0.0])]
    for case in range(20000):
        acc = rng.normal(size=3) * (1e-3, 0.5, 3.0, 30.0)[case % 4]
        if case % 101 == 0:
            acc[case % 3] = np.nan
        cases.append(acc)
    for k, acc in enumerate(cases):
        yaw = float(rng.normal()) * 3.0
        want = np.array(_accel_to_attitude_array(acc, yaw, 0.5))
        att = accel_to_attitude(acc, yaw, 0.5)
        got = np.array([att.roll_rad, att.pitch_rad, att.yaw_rad, att.thrust_norm])
        assert np.array_equal(want.view(np.uint64), got.view(np.uint64)), (k, acc)


def test_a_hit_enters_compiled_code_once_for_theta_and_the_check(monkeypatch):
    """On the EPC's hit path θ and the last controller's KKT check are one compiled call
    (``kernels.theta_check``): the check's own entry (``apply_map``, a second machinery a
    cold tick paid for; issue 21) is not called. And LWPR's query, the filter's step, the
    plan and x0 are one compiled call (``kernels.lwpr_plan``), and with θ and the check
    the same call (``kernels.plan_step``: the controller's own θ entry, ``theta_compiled``,
    not called). The commands are the separate calls' to the last bit: the same ticks
    flown with θ's call refused (the plan and θ + check as two calls), or the plan refused
    (its Python path), give the same sources, commands, quaternions and estimates."""
    from epc_offboard.control import kernels
    from epc_offboard.control.epc import maps

    if not kernels.HAVE_NUMBA:
        pytest.skip("numba is not in use: the numpy code is all there is")
    traj = Trajectory(TrajectoryConfig(shape="figure8", ramp_s=1.0, period_s=8.0),
                      np.array([0.0, 0.0, -2.5]))  # fmt: skip
    runs: dict[str, list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]] = {}
    for variant in ("fused", "theta refused", "plan refused"):
        cascade, _tick = _figure8_ticks()
        loop = cascade.position
        controller: Any = loop.controller
        if variant == "theta refused":
            controller._theta_check = None
        outs: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
        for k in range(500):
            if k == 400:
                checks: list[int] = []
                real = kernels.apply_map  # what maps calls (its own import of it)

                def counting(*args: Any, _real: Any = real, _checks: list[int] = checks) -> Any:
                    _checks.append(1)
                    return _real(*args)

                monkeypatch.setattr(maps, "apply_map", counting)
                stacked: list[int] = []
                real_theta = controller.theta_compiled

                def stacking(*args: Any, _real: Any = real_theta,
                             _stacked: list[int] = stacked) -> Any:
                    _stacked.append(1)
                    return _real(*args)

                monkeypatch.setattr(controller, "theta_compiled", stacking)
            if variant == "plan refused" and k >= 1:
                loop._lwpr_plan = None  # (made with the plan at the first tick: refused)
            state, reference = _figure8_inputs(traj, loop, k)
            out = cascade.position_tick(state, reference, learn=True)
            outs.append((out.source, out.acc_cmd_ned_m_s2.copy(), out.q_target.copy(),
                         out.p_hat_ned_m_s2.copy()))  # fmt: skip
        monkeypatch.undo()
        hits = sum(o[0] == "hit" for o in outs[400:])
        assert hits > 50
        if variant == "theta refused":
            assert len(checks) >= hits - 1  # (the refused path checks the last as before)
        else:
            assert not checks, f"apply_map called {len(checks)} times on {hits} hits"
        if variant == "fused":
            assert loop._lwpr_plan is not None
            assert loop._plan_step is not None
            assert not stacked, f"theta_compiled called {len(stacked)} times in 100 ticks"
        else:
            assert len(stacked) == 100
        runs[variant] = outs
    for variant in ("theta refused", "plan refused"):
        for k, (a, b) in enumerate(zip(runs["fused"], runs[variant], strict=True)):
            assert a[0] == b[0], (variant, k)
            for x, y in zip(a[1:], b[1:], strict=True):
                assert np.array_equal(x.view(np.uint64), y.view(np.uint64)), (variant, k)


def _captured_ticks(variant: str, position: Any, path: tuple[str, str] | None,
                    ticks: int) -> list[tuple[Any, ...]]:
    """The figure-8's ticks with ``position``'s config and ``path``'s dead time, the plan
    compiled (``fused``) or refused from the second tick (``refused``: the Python path,
    the window, BLAS's products); per tick what the EPC step was given and the output."""
    cfg = load_service_config(_CONFIG)
    cascade = Cascade(position, cfg.attitude, cfg.estimator, _DT_S, learn_on_miss=True,
                      airframe=cfg.vehicle)  # fmt: skip
    cascade.warm_up()
    loop = cascade.position
    if path is not None:
        loop.use_attitude_path(*path)
    controller: Any = loop.controller
    # (what the EPC step is given is compared: θ stacked in the step, not in the plan's
    # call, kernels.plan_step; test_a_hit_enters_compiled_code_once... compares the two)
    controller._theta_check = None
    given: list[tuple[np.ndarray, ...]] = []
    real_step = controller.step

    def step(x0: Any, refs: Any, u_p: Any, *, perturbation: Any) -> Any:
        given.append((np.array(x0), np.array(refs), np.array(u_p), np.array(perturbation)))
        return real_step(x0, refs, u_p, perturbation=perturbation)

    controller.step = step
    traj = Trajectory(TrajectoryConfig(shape="figure8", ramp_s=1.0, period_s=8.0),
                      np.array([0.0, 0.0, -2.5]))  # fmt: skip
    outs: list[tuple[Any, ...]] = []
    for k in range(ticks):
        if variant == "refused" and k >= 1:
            loop._lwpr_plan = None
        state, reference = _figure8_inputs(traj, loop, k, loop.config.reference_steps)
        out = cascade.position_tick(state, reference, learn=True)
        outs.append((out.source, *given[-1], out.acc_cmd_ned_m_s2.copy(), out.q_target.copy(),
                     out.p_hat_ned_m_s2.copy()))  # fmt: skip
    if variant == "fused":
        assert loop._lwpr_plan is not None
    return outs


@pytest.mark.parametrize("case", ["px4 quaternion", "px4 body rates", "fractional",
                                  "no dead time"])
def test_the_compiled_plan_carries_x0_over_the_dead_time_as_the_python_path(case):
    """The position tick's compiled plan (``kernels.lwpr_plan``) makes the reference window,
    carries x0 over the command dead time and makes the perturbation ``E d_hat`` itself
    (issue 21: the window's indexing and three BLAS products were machineries a cold tick
    paid for). Against the Python path (``DeadTimePredictor.window`` and ``ahead``, numpy's
    ``E @ d_hat``), tick by tick over a figure-8 (whole and fractional leads, commands in
    flight and missing at entry): the window and the plan bit for bit, x0, the
    perturbation and the commands within 1e-12 relative (the products summed in order,
    not in BLAS's blocks), the same sources."""
    from dataclasses import replace

    from epc_offboard.control import kernels

    if kernels.lwpr_plan is None:
        pytest.skip("numba is not in use: the Python path is all there is")
    cfg = load_service_config(_CONFIG)
    position, path = cfg.position, None
    if case == "px4 quaternion":
        path = ("px4", "autopilot")  # 0.15 s: 3 whole stages of the window, 15 commands
    elif case == "px4 body rates":
        path = ("px4", "epc")  # 0.05 s: 1 stage, 5 commands
    elif case == "fractional":  # 0.4 of a stage past 2; a command in flight half a tick
        position = replace(position, command_dead_time_s=0.12, state_latency_s=0.015)
    else:
        position = replace(position, command_dead_time_s=0.0)
    fused = _captured_ticks("fused", position, path, 300)
    refused = _captured_ticks("refused", position, path, 300)
    worst = 0.0
    for k, (a, b) in enumerate(zip(fused, refused, strict=True)):
        assert a[0] == b[0], (k, a[0], b[0])
        x0_a, refs_a, u_p_a, pert_a, *out_a = a[1:]
        x0_b, refs_b, u_p_b, pert_b, *out_b = b[1:]
        if k < 2:  # before any command differs in its last bits: the window and plan exact
            assert np.array_equal(refs_a, refs_b), k
            assert np.array_equal(u_p_a, u_p_b), k
        for x, y in ((x0_a, x0_b), (pert_a, pert_b), (refs_a, refs_b), (u_p_a, u_p_b),
                     *zip(out_a, out_b, strict=True)):  # fmt: skip
            scale = max(float(np.max(np.abs(y))), 1e-300)
            worst = max(worst, float(np.max(np.abs(x - y))) / scale)
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12 * scale, err_msg=str(k))
    assert sum(o[0] == "hit" for o in fused) > 100
    if case == "no dead time":
        assert worst == 0.0  # (3-term products: the sums BLAS takes too)


def test_a_tick_touches_neither_the_dead_time_in_python_nor_numbas_unpickler(monkeypatch):
    """On the compiled path the tick calls no ``DeadTimePredictor.window`` or ``ahead``
    (their work is in the compiled plan), and no compiled call unboxes a numba typed list:
    numba unboxes one by calling back into Python (``numba.core.serialize._numba_unpickle``,
    ~45 us of a cold tick, issue 21); the LWPR kernels take the list's memory handle."""
    from epc_offboard.control import kernels
    from epc_offboard.control.dead_time import DeadTimePredictor

    if kernels.lwpr_plan is None:
        pytest.skip("numba is not in use")
    cascade, tick = _figure8_ticks()
    cascade.position.use_attitude_path("px4", "autopilot")
    for k in range(60):
        tick(k)
    called: Counter[str] = Counter()
    for name in ("window", "ahead"):
        real = getattr(DeadTimePredictor, name)

        def counting(*args: Any, _real: Any = real, _name: str = name) -> Any:
            called[_name] += 1
            return _real(*args)

        monkeypatch.setattr(DeadTimePredictor, name, counting)

    def profile(frame: Any, event: str, arg: Any) -> None:
        if event == "call":
            called[frame.f_code.co_name] += 1

    sys.setprofile(profile)
    try:
        for k in range(60, 80):
            tick(k)
    finally:
        sys.setprofile(None)
    made = (called["window"], called["ahead"], called["_numba_unpickle"])
    assert made == (0, 0, 0), f"window, ahead, _numba_unpickle calls: {made}"
    assert called["position_tick"] >= 20  # (the profile saw the ticks)
