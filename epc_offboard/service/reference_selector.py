"""Which reference the position loop tracks, tick by tick.

In offboard, a fresh live reference from a planner (``[reference] source = "zenoh"``) comes
first; else the mission's trajectory, closing the gap to it after a hold (a failsafe, a
pilot) with a :class:`~epc_offboard.control.trajectories.Rejoin`; else the hold point (the
trajectory's anchor, or where the vehicle was when there was nothing else). Whichever it is
arrives as one :class:`~epc_offboard.control.types.ReferenceHorizon`: the position tick
flies it and the flight log reads the reference now from it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import Counter

import numpy as np

from epc_offboard.common.frames import FloatArray
from epc_offboard.control.position import PositionControlConfig
from epc_offboard.control.trajectories import (
    Rejoin,
    Trajectory,
    TrajectoryConfig,
    live_reference_horizon,
)
from epc_offboard.control.types import ReferenceHorizon, VehicleState
from epc_offboard.fleet.sharing import FleetSharing

log = logging.getLogger("epc_offboard.service")


class ReferenceSelector:
    """Chooses the reference horizon of each position tick (the service's, one per vehicle),
    and owns the mission's trajectory.

    ``position``: the horizon's length, step and default heading; ``trajectory_cfg``: the
    mission's trajectory, started once offboard (:meth:`start_trajectory`) at the altitude
    ``trajectory_altitude_m`` above home (None: where the vehicle is); ``live_timeout_s``: a
    live reference older than this (wall time) is stale; ``counters``: the service's, where
    the rejoins and stale live references are counted.
    """

    def __init__(
        self,
        position: PositionControlConfig,
        trajectory_cfg: TrajectoryConfig,
        trajectory_altitude_m: float | None,
        live_timeout_s: float,
        counters: Counter[str],
    ) -> None:
        self.position = position
        self.trajectory_cfg = trajectory_cfg
        self.trajectory_altitude_m = trajectory_altitude_m
        self.live_timeout_s = live_timeout_s
        self.counters = counters
        self.trajectory: Trajectory | None = None
        self.rejoin: Rejoin | None = None  # the way back onto the trajectory after a hold
        self._hold_pos: FloatArray | None = None
        self._live = False  # whether the last horizon came from a live reference

    def start_trajectory(
        self, state: VehicleState, altitude_m: float | None, now_s: float
    ) -> None:
        """Offboard is confirmed: the trajectory starts here, at its altitude above home
        (``altitude_m``: the vehicle's height above home now, if known)."""
        anchor = state.pos_ned_m.copy()
        want = self.trajectory_altitude_m
        if want is not None and altitude_m is not None:
            anchor[2] += altitude_m - want  # down of home = down now + height above home
        self.trajectory = Trajectory(self.trajectory_cfg, anchor, start_s=now_s)
        self.hold_at(anchor)
        log.info("trajectory %s started at %s", self.trajectory_cfg.shape,
                 anchor.round(3).tolist())  # fmt: skip
        # from where the vehicle is, closing the gap (e.g. to the altitude) smoothly: a
        # step in the reference at entry is a jolt however calm the controller
        self.start_rejoin(state, now_s)

    def mission_complete(self, now_s: float, duration_s: float) -> bool:
        """Whether the trajectory has been flown ``duration_s`` (> 0) seconds."""
        traj = self.trajectory
        return traj is not None and duration_s > 0 and now_s - traj.start_s >= duration_s

    def reload(self, trajectory_cfg: TrajectoryConfig, now_s: float) -> None:
        """A new trajectory configuration (SIGHUP): a running trajectory restarts with it
        from its anchor."""
        self.trajectory_cfg = trajectory_cfg
        if self.trajectory is not None:
            self.trajectory = Trajectory(trajectory_cfg, self.trajectory.anchor_ned_m, now_s)

    def hold_at(self, pos_ned_m: FloatArray) -> None:
        """Hold ``pos_ned_m`` (3,) m when there is no trajectory nor live reference."""
        self._hold_pos = np.asarray(pos_ned_m, dtype=np.float64).copy()

    def start_rejoin(self, state: VehicleState, now_s: float) -> None:
        """Setpoints start streaming, or offboard is (re)entered, while a trajectory has run
        on (a failsafe, a pilot): the reference starts where the vehicle is and closes the
        gap smoothly (trajectories.Rejoin) instead of asking for a far point at once."""
        trajectory = self.trajectory
        if trajectory is None:
            return
        rejoin = Rejoin.onto(
            trajectory.sample(now_s), state.pos_ned_m, state.vel_ned_m_s, now_s,
            trajectory.config.rejoin_tau_s,
        )  # fmt: skip
        # Vertically the gap closes from rest: a climb still under way (ArduCopter's takeoff
        # hands over at 2.4 m climbing 1.5 m/s) is braked with thrust alone at once, not
        # carried on by the reference (0.75 m above the entry); horizontally the gap keeps
        # its rate, a tilt the vehicle already flies.
        rate = rejoin.gap_rate_ned_m_s.copy()
        rate[2] = 0.0
        # no faster than half the entry ramp's acceleration budget asks: the trajectory's
        # own acceleration and the wind's share the rest
        self.rejoin = dataclasses.replace(rejoin, gap_rate_ned_m_s=rate).within(
            0.5 * self.position.entry_max_acc_m_s2
        )
        gap = float(np.linalg.norm(self.rejoin.gap_ned_m))
        if gap > 0.05:
            self.counters["trajectory_rejoins"] += 1
            log.info("rejoining the trajectory %.2f m away (tau %.1f s)", gap,
                     self.rejoin.tau_s)  # fmt: skip

    def horizon(
        self, state: VehicleState, t_s: float, sharing: FleetSharing | None, *, offboard: bool
    ) -> ReferenceHorizon:
        """The position tick's reference at loop time ``t_s``: a fresh live reference from
        ``sharing`` (``offboard`` only), else the trajectory (rejoin included), else the
        hold."""
        live = self._live_horizon(state, sharing, offboard=offboard)
        if live is not None:
            return live
        if not offboard and self.trajectory is None:
            # Before offboard is confirmed the autopilot may still be climbing out of its
            # takeoff, or already flying ours (PX4 shows the mode up to 1 s late): hold
            # where the vehicle is now, at rest, not where it was when streaming started
            # (0.45 m below it after a takeoff overshoot: the vehicle dropped to it).
            self.hold_at(state.pos_ned_m)
        return self.now(state, t_s, steps=self.position.reference_steps)

    def now(self, state: VehicleState, t_s: float, *, steps: int = 0) -> ReferenceHorizon:
        """The trajectory (rejoin included) or the hold, over stages 0..``steps`` from ``t_s``
        (the default, stage 0 only: the reference now, as the px4 baseline sends it)."""
        yaw_rad = self.position.yaw_rad
        trajectory = self.trajectory
        if trajectory is None:
            if self._hold_pos is None:
                self._hold_pos = state.pos_ned_m.copy()
            return ReferenceHorizon.hold(self._hold_pos, yaw_rad, steps)
        if self.rejoin is not None and self.rejoin.done(t_s):
            self.rejoin = None
        return trajectory.reference(t_s, self.position.dt_s, steps, yaw_rad, self.rejoin)

    def _live_horizon(
        self, state: VehicleState, sharing: FleetSharing | None, *, offboard: bool
    ) -> ReferenceHorizon | None:
        """The horizon from a fresh live reference (offboard only), else None."""
        ref = None
        if sharing is not None and offboard:
            ref = sharing.live_reference(time.monotonic(), self.live_timeout_s)
        if (ref is not None) != self._live:
            self._live = ref is not None
            if ref is not None:
                log.info("live reference: tracking from %s", list(ref.message.pos_ned_m))
            elif sharing is not None:
                self.counters["live_reference_stale"] += 1
                log.warning(
                    "live reference stale (> %.2f s): back to the %s",
                    self.live_timeout_s,
                    "trajectory" if self.trajectory is not None else "hold",
                )
                if self.trajectory is None:
                    self.hold_at(state.pos_ned_m)
        if ref is None:
            return None
        msg = ref.message
        return live_reference_horizon(
            msg.pos_ned_m,
            msg.vel_ned_m_s,
            msg.horizon_pos_ned_m,
            msg.horizon_dt_s,
            yaw_rad=self.position.yaw_rad if msg.yaw_rad is None else msg.yaw_rad,
            age_s=time.monotonic() - ref.received_s,
            dt_s=self.position.dt_s,
            steps=self.position.reference_steps,
        )
