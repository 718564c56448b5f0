"""The position tick's stages, thread CPU, with warm and with cold caches (issue 21).

``python -m epc_offboard.tools.tick_stages [--ticks N] [--config PATH]``

In real time a position tick costs ~3x its lockstep cost, all of it work on the CPU: 10 ms
after the last tick its code and data are no longer in the caches (``service/realtime.py``).
This drives the service's position tick (:class:`~epc_offboard.control.cascade.Cascade`,
the configuration's estimator and EPC library, a figure-8's reference, a new position
sample every other tick as at 50 Hz, the flight-log row packed) and times each stage with
the thread's CPU clock, three ways: ``warm`` (ticks back to back, as lockstep runs them),
``sleep`` (10 ms between ticks, as the loop's period) and ``evict`` (a 64 MB buffer read
between ticks: every cache level cold, the worst case, repeatable whatever the machine's
load). The stages that grow most from warm to cold are what to cut: each stage is a
method wrapped where the tick calls it (the wrappers' own cost is in the figures, the
same for every run).

Thread CPU, not wall time: the load of other processes does not stretch it (it does evict
caches, which is what ``evict`` shows at its worst).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from epc_offboard.common import frames
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.models import accel_to_attitude
from epc_offboard.control.trajectories import Trajectory, TrajectoryConfig
from epc_offboard.control.types import VehicleState
from epc_offboard.service.config import load_service_config
from epc_offboard.service.flightlog import pack_row

MODES = ("warm", "sleep", "evict")
_DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "config" / "sitl.toml"
_EVICT_DOUBLES = 8 * 1024 * 1024  # 64 MB: twice the largest last-level cache met (32 MB)


def _state(t_s: float, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
           position_age_s: float) -> VehicleState:
    att = accel_to_attitude(acc, 0.0, 0.5)  # tilted for the acceleration it flies
    return VehicleState(
        time_s=t_s, pos_ned_m=pos, vel_ned_m_s=vel,
        q_ned_frd=frames.euler_to_quat(att.roll_rad + 0.02, att.pitch_rad - 0.03, 0.0),
        rate_frd_rad_s=np.zeros(3), position_age_s=position_age_s, attitude_age_s=0.0,
    )  # fmt: skip


class _Stages:
    """Thread CPU (ns) per stage over the tick in progress."""

    def __init__(self) -> None:
        self.tick: dict[str, int] = {}
        self._wrapped: list[tuple[Any, str, Any]] = []

    def restore(self) -> None:
        """Unwrap everything (a module's function wrapped is every caller's)."""
        for owner, method, fn in reversed(self._wrapped):
            setattr(owner, method, fn)
        self._wrapped.clear()

    def wrap(self, owner: Any, method: str, name: str) -> None:
        fn: Callable[..., Any] = getattr(owner, method)
        self._wrapped.append((owner, method, fn))
        tick, clock = self.tick, time.thread_time_ns

        def timed(*args: Any, **kw: Any) -> Any:
            t0 = clock()
            out = fn(*args, **kw)
            tick[name] = tick.get(name, 0) + clock() - t0
            return out

        setattr(owner, method, timed)


def _wrap_fine(stages: _Stages, loop: Any) -> None:
    """``--fine``: the tick's smaller steps too (each wrapper's own cold cost with them)."""
    from epc_offboard.control import position

    for name in ("attitude_to_axis_xyz", "limit_tilt", "disturbance_plan"):
        if getattr(position, name, None) is not None:
            stages.wrap(position, name, name)
    # (on the compiled plan's path the window and the carry over the dead time run inside
    # it, kernels.lwpr_plan: these two then show nothing)
    stages.wrap(loop.dead_time, "window", "dead_time.window")
    stages.wrap(loop.dead_time, "ahead", "dead_time.ahead")
    stages.wrap(loop.dead_time, "sent", "dead_time.sent")
    stages.wrap(loop._state_filter, "update", "state_filter")
    stages.wrap(loop, "achieved_acceleration", "achieved_acceleration")
    stages.wrap(loop, "_entry_ramp", "entry_ramp")
    stages.wrap(loop.estimator, "observe", "estimator.observe")
    controller: Any = loop.controller
    stages.wrap(controller, "decide", "epc.decide")


def measure(config: Path, ticks: int, modes: tuple[str, ...] = MODES,
            fine: bool = False, path: tuple[str, str] | None = None) -> dict[str, Any]:
    """Per mode: the mean and median thread CPU (us) of each stage over ``ticks`` ticks
    (a stage that runs every other tick: its mean over the ticks that ran it); ``fine``:
    the smaller steps too; ``path``: (autopilot, attitude mode) whose command dead time the
    tick flies, as the service sets it (unset: the configuration's, 0 if it sets none)."""
    cfg = load_service_config(config)
    dt_s = 1.0 / cfg.loops.position_rate_hz
    cascade = Cascade(cfg.position, cfg.attitude, cfg.estimator, dt_s, learn_on_miss=True,
                      airframe=cfg.vehicle)  # fmt: skip
    cascade.warm_up()
    loop = cascade.position
    if path is not None:
        loop.use_attitude_path(*path)
    traj = Trajectory(TrajectoryConfig(shape="figure8", ramp_s=1.0, period_s=8.0),
                      np.array([0.0, 0.0, -2.5]))  # fmt: skip
    stages = _Stages()
    clock = time.thread_time_ns

    def tick(k: int) -> str:
        t_s = 1.0 + k * dt_s
        age_s = (k % 2) * dt_s  # a new position sample every other tick
        now = traj.sample(t_s - age_s)
        state = _state(t_s, now.pos_ned_m + 0.01, now.vel_ned_m_s * 0.98, now.acc_ned_m_s2,
                       age_s)  # fmt: skip
        t0 = clock()
        reference = traj.reference(t_s, loop.config.dt_s, loop.config.horizon, 0.0)
        t1 = clock()
        out = cascade.position_tick(state, reference, learn=True)
        t2 = clock()
        pack_row(t_s, "offboard", state, reference, out)
        t3 = clock()
        stages.tick["reference"] = t1 - t0
        stages.tick["position_tick"] = t2 - t1
        stages.tick["pack_row"] = t3 - t2
        return out.source

    k = 0
    for k in range(400):  # the library learns the figure-8's controllers
        tick(k)
    # inside the tick: the estimator (learning, prediction), the EPC step (θ, the library
    # query, the rest of the decision), the attitude map
    stages.wrap(loop, "observe", "observe")
    controller: Any = loop.controller
    plan = loop._filtered_plan()
    if plan is not None and loop._plan_step is not None:
        # LWPR's prediction, its filter's step, the plan, x0, θ and the EPC's check of the
        # last controller: one compiled call (kernels.plan_step); the EPC step's rest
        stages.wrap(loop, "_plan_step", "plan_step")
        stages.wrap(controller, "decide", "epc.step")
    else:
        if plan is None:
            stages.wrap(loop.estimator, "estimate_along", "estimate_along")
        elif loop._lwpr_plan is not None:  # LWPR's prediction, its filter's step, the plan
            stages.wrap(loop, "_lwpr_plan", "estimate_along")  # and x0: one compiled call
        else:  # LWPR's prediction along the horizon; its filter's step in the compiled plan
            stages.wrap(loop.estimator, "predict_raw_many", "estimate_along")
        from epc_offboard.control import kernels
        from epc_offboard.control.epc import controller as epc

        if isinstance(controller, epc.ExperienceController) and kernels.stack_theta is not None:
            stages.wrap(controller, "theta_compiled", "epc.theta")  # (the compiled stack)
        else:
            stages.wrap(controller.problem, "theta", "epc.theta")
        stages.wrap(controller, "step", "epc.step")
    if hasattr(controller, "library"):
        stages.wrap(controller.library, "query", "epc.query")
    stages.wrap(loop, "_attitude_target", "attitude_target")
    if fine:
        _wrap_fine(stages, loop)
    try:
        return _run(stages, tick, k, modes, ticks, dt_s)
    finally:
        stages.restore()


def _run(stages: _Stages, tick: Callable[[int], str], k: int, modes: tuple[str, ...],
         ticks: int, dt_s: float) -> dict[str, Any]:
    buffer = np.ones(_EVICT_DOUBLES)
    report: dict[str, Any] = {}
    for mode in modes:
        samples: dict[str, list[int]] = {}
        sources: dict[str, int] = {}
        for _ in range(ticks):
            k += 1
            if mode == "evict":
                buffer.sum()
            elif mode == "sleep":
                time.sleep(dt_s)
            stages.tick.clear()
            source = tick(k)
            sources[source] = sources.get(source, 0) + 1
            for name, ns in stages.tick.items():
                samples.setdefault(name, []).append(ns)
        report[mode] = {
            "sources": sources,
            "stages_us": {
                name: {"mean": float(np.mean(v)) / 1e3, "median": float(np.median(v)) / 1e3,
                       "ticks": len(v)}
                for name, v in samples.items()
            },
        }  # fmt: skip
    return report


def format_report(report: dict[str, Any]) -> str:
    modes = list(report)
    names = sorted(report[modes[0]]["stages_us"],
                   key=lambda n: -report[modes[-1]]["stages_us"][n]["mean"])  # fmt: skip
    lines = ["stage (thread CPU, mean us)".ljust(28) + "".join(m.rjust(10) for m in modes)]
    for name in names:
        lines.append(name.ljust(28) + "".join(
            f"{report[m]['stages_us'].get(name, {}).get('mean', float('nan')):10.1f}"
            for m in modes))  # fmt: skip
    lines.append("position_tick median".ljust(28) + "".join(
        f"{report[m]['stages_us']['position_tick']['median']:10.1f}" for m in modes))
    lines.append("sources: " + "; ".join(f"{m} {report[m]['sources']}" for m in modes))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=_DEFAULT_CONFIG)
    parser.add_argument("--ticks", type=int, default=1500)
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--fine", action="store_true", help="the tick's smaller steps too")
    parser.add_argument("--attitude-path", metavar="AUTOPILOT,MODE",
                        help="fly this path's command dead time as the service does, e.g. "
                             "px4,autopilot (quaternion: bench --attack's) or px4,epc")  # fmt: skip
    args = parser.parse_args(argv)
    modes = tuple(m for m in args.modes.split(",") if m)
    if not set(modes) <= set(MODES) or not modes:
        parser.error(f"--modes: some of {', '.join(MODES)}")
    path = None
    if args.attitude_path:
        autopilot, _, mode = args.attitude_path.partition(",")
        if autopilot not in ("px4", "ardupilot") or mode not in ("autopilot", "epc"):
            parser.error("--attitude-path: px4|ardupilot,autopilot|epc")
        path = (autopilot, mode)
    print(format_report(measure(args.config, args.ticks, modes, args.fine, path)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
