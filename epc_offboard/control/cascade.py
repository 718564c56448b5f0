"""The control cascade: what one tick of the position loop and of the attitude loop compute.

Pure numerics (no asyncio, no MAVLink): the service hands in a VehicleState and references
and gets back setpoints.

Position loop (100 Hz), :meth:`Cascade.position_tick`:

1. learn: the acceleration disturbance measured over the last prediction step,
   ``d = (v_k - v_{k-n}) / dt - mean(a_achieved)``, where ``a_achieved`` is what the measured
   attitude and the commanded thrust produce — so attitude-loop lag is not mistaken for wind;
   the estimator (LWPR on velocity, a Kalman observer, or none) is updated with it at the
   mean velocity over the same window;
2. predict: ``d_hat`` = the estimator's low-pass-filtered estimate at the current velocity,
   and ``d_k = d_hat + variation(v_ref[k])`` along the horizon (LWPR's learned d(v) at each
   stage's reference velocity; no variation for the Kalman observer);
3. model: x = [p_ned, v_ned, a_ned] with ``a`` the acceleration the attitude and thrust
   produce, following the command u = a_cmd with the inner loop's first-order lag
   ``tau_acc_s`` (:func:`~epc_offboard.control.models.position_model_lagged`);
   ``x[k+1] = A x[k] + B u[k] + c~`` with ``c~ = c + E d_hat`` (thesis 3.1.1: the
   perturbation enters the affine model; E: how an acceleration disturbance enters v), and
   per stage ``u_p[k]``: the command that makes the lagged acceleration follow
   ``a_ref - d_k`` — the reference's feedforward plus the input that cancels the disturbance
   expected at that stage — so the input penalty fights neither;
4. control: EPC (or PD / MPC-every-tick) over the reference horizon -> ``a_cmd``;
5. map: ``a_cmd`` -> roll, pitch, yaw, thrust (thesis eq. 3.13, exact inverse, NED).

Attitude loop (200 Hz), :meth:`Cascade.attitude_tick`: EPC on x = [roll, pitch, yaw, p, q, r]
with body-rate commands as input and a first-order rate response (the autopilot's rate loop),
reference = the position loop's attitude with zero rates -> body rates + thrust.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from epc_offboard.common import frames
from epc_offboard.common.frames import GRAVITY_M_S2, FloatArray
from epc_offboard.control import kernels, lwpr, trajectories
from epc_offboard.control.baselines import MpcController, PdController
from epc_offboard.control.decision import Controller, Decision
from epc_offboard.control.epc import ExperienceController
from epc_offboard.control.library import (
    LibraryEntry,
    LibrarySnapshot,
    SignatureSnapshot,
    Transition,
)

# the names this module used before library.py held one entry type and the store's protocol
# (kept to leave the concurrent split of this module undisturbed; rename after it lands)
from epc_offboard.control.library import LibraryEntry as StoredController
from epc_offboard.control.library import LibraryStorage as LibraryStore
from epc_offboard.control.models import (
    AttitudeThrust,
    accel_to_attitude,
    acceleration_limits,
    attitude_model,
    attitude_to_accel,
    limit_tilt,
    position_model_lagged,
    velocity_disturbance_input,
)
from epc_offboard.control.perturbation import (
    KalmanPerturbationConfig,
    LwprPerturbationConfig,
    PerturbationConfig,
    make_estimator,
)
from epc_offboard.control.qp import MpcProblem
from epc_offboard.vehicle.state import VehicleState

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class PositionControlConfig:
    # px4: a baseline, the autopilot's own position controller flies the reference
    # (SET_POSITION_TARGET_LOCAL_NED with position, velocity and acceleration)
    controller: Literal["epc", "pd", "mpc", "px4"] = "epc"
    horizon: int = 20
    dt_s: float = 0.05  # prediction step, separate from the loop period
    q_pos: Vec3 = (20.0, 20.0, 30.0)
    q_vel: Vec3 = (3.0, 3.0, 3.0)
    q_acc: Vec3 = (0.0, 0.0, 0.0)  # weight on the achieved-acceleration error
    # inner-loop lag from commanded to achieved acceleration, first order, per NED axis:
    # horizontally the attitude loop's response (identified on the bundled SITL from
    # commanded vs ground-truth acceleration), vertically the motors' (thrust is direct)
    tau_acc_s: Vec3 = (0.12, 0.12, 0.03)
    r_acc: Vec3 = (0.3, 0.3, 0.3)
    max_vel_m_s: Vec3 = (3.8, 3.8, 2.0)  # state constraint |v_i| <= max (thesis zig-zag: 3.8)
    geofence_min_ned_m: Vec3 | None = None  # optional position box
    geofence_max_ned_m: Vec3 | None = None
    max_tilt_deg: float = 45.0  # PX4's MPC_TILTMAX_AIR default
    hover_thrust_norm: float = 0.5  # PX4's MPC_THR_HOVER
    min_thrust_norm: float = 0.08
    max_thrust_norm: float = 0.95
    yaw_deg: float = 0.0  # heading held while tracking
    library_size: int = 400
    # a library query's worst-case cost: bounds the candidates a miss checks (the most
    # likely first: the last controller, its successors, then by importance). 3000 us of the
    # worst-case model is ~190 position maps (a check usually exits within a few rows, at a
    # fraction of that); 400 us (25 maps) left a saved library's controllers unchecked: a
    # second zig-zag flight missed 122 ticks instead of 42, and a miss costs more than the
    # checks it saves (the intermediate QP on the loop and a solve in the worker)
    query_budget_us: float = 3000.0
    pd_kp: Vec3 = (6.0, 6.0, 8.0)
    pd_kd: Vec3 = (4.5, 4.5, 5.0)

    def __post_init__(self) -> None:
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")
        if self.dt_s <= 0.0:
            raise ValueError(f"dt_s must be > 0, got {self.dt_s}")
        if any(v <= 0.0 for v in self.max_vel_m_s):
            raise ValueError(f"max_vel_m_s must be > 0, got {self.max_vel_m_s}")
        if any(not t > 0.0 for t in self.tau_acc_s):
            raise ValueError(f"tau_acc_s must be > 0, got {self.tau_acc_s}")
        if any(q < 0.0 for q in (*self.q_pos, *self.q_vel, *self.q_acc)):
            raise ValueError("q_pos, q_vel and q_acc must be >= 0")
        if not 0.0 < self.min_thrust_norm < self.hover_thrust_norm < self.max_thrust_norm <= 1.0:
            raise ValueError("need 0 < min_thrust_norm < hover_thrust_norm < max_thrust_norm <= 1")
        if self.library_size < 1:
            raise ValueError(f"library_size must be >= 1, got {self.library_size}")
        if not self.query_budget_us > 0.0:
            raise ValueError(f"query_budget_us must be > 0, got {self.query_budget_us}")


@dataclass(frozen=True)
class AttitudeControlConfig:
    # epc: body rates from the attitude EPC; autopilot: quaternion + thrust to its own loop;
    # auto: epc on PX4, autopilot on ArduPilot (ArduCopter shapes body-rate targets with
    # ATC_INPUT_TC, so its rate response is not the identified first-order rate model)
    mode: Literal["auto", "epc", "autopilot"] = "auto"
    horizon: int = 10
    dt_s: float = 0.01
    rate_time_constant_s: float = 0.03  # the autopilot's rate loop, first order
    q_angle: Vec3 = (60.0, 60.0, 20.0)
    q_rate: Vec3 = (0.3, 0.3, 0.3)
    r_rate: Vec3 = (0.02, 0.02, 0.05)
    max_rate_rad_s: Vec3 = (4.0, 4.0, 2.0)
    fallback_gain_1_s: float = 6.0  # P on angle error when the attitude EPC cannot answer
    library_size: int = 200
    query_budget_us: float = 200.0  # as position.query_budget_us
    # The attitude EPC is linearised about hover (Euler angles, body rates). Beyond this tilt,
    # or this far from its attitude target, its body rates are not to be trusted (in a soak
    # under CPU load it chattered between +-max rate at 60 deg and flipped the vehicle): the
    # attitude goes to the autopilot's own (quaternion) attitude loop until back inside.
    rates_max_tilt_deg: float = 55.0
    rates_max_error_deg: float = 35.0

    def __post_init__(self) -> None:
        if self.horizon < 1 or self.dt_s <= 0.0 or self.rate_time_constant_s <= 0.0:
            raise ValueError("horizon >= 1, dt_s > 0 and rate_time_constant_s > 0 are required")
        if any(v <= 0.0 for v in self.max_rate_rad_s):
            raise ValueError(f"max_rate_rad_s must be > 0, got {self.max_rate_rad_s}")
        if not self.query_budget_us > 0.0:
            raise ValueError(f"query_budget_us must be > 0, got {self.query_budget_us}")
        for name in ("rates_max_tilt_deg", "rates_max_error_deg"):
            if not 0.0 < getattr(self, name) <= 180.0:
                raise ValueError(f"{name} must be in (0, 180], got {getattr(self, name)}")


def _default_lwpr() -> LwprPerturbationConfig:
    # z = velocity (m/s), p = acceleration disturbance (m/s^2).
    # inputs: each axis's disturbance learned on that axis's velocity (thesis 3.1.1: the
    #   subspace the disturbance depends on). Drag acts along the airspeed, and a multirotor's
    #   horizontal drag is the same along north and east, so d_i depends on v_i; a full 3-D
    #   input makes incremental PLS split each local model over three projections, which
    #   converges far slower on noisy targets (figure-8: 4-6 cm/s^2 error against 0.4-0.9).
    # init_d = 4 on these norms: fields about 2 m/s (1 m/s vertically) wide. Drag varies
    #   smoothly with airspeed, so one local linear model spans the usual envelope and new
    #   fields grow only beyond it; narrow fields each start from scratch and blend in
    #   half-trained.
    # lowpass 5 Hz (time constant 32 ms, below the inner loop's lag): the prediction is a
    #   function of the measured velocity, not a raw measurement, so it needs little
    #   smoothing; a 1 Hz filter lagged the figure-8's drag by 0.16 s (3 cm/s^2 error).
    return LwprPerturbationConfig(
        inputs=((0,), (1,), (2,)),
        norm_z=(4.0, 4.0, 2.0),
        norm_p=(1.0, 1.0, 1.0),
        init_d=4.0,
        lowpass_cutoff_hz=5.0,
    )


@dataclass(frozen=True)
class EstimatorConfig:
    """The acceleration-disturbance estimator of the position loop (thesis 3.1.1).

    It learns d (3,) m/s^2 from the velocity (3,) m/s: the thesis's subspace example, and
    what wind acting through drag depends on. ``dt_s`` of the sub-tables is set from the
    position loop's period.
    """

    kind: Literal["none", "lwpr", "kf"] = "lwpr"
    lwpr: LwprPerturbationConfig = field(default_factory=_default_lwpr)
    kf: KalmanPerturbationConfig = field(default_factory=KalmanPerturbationConfig)


@dataclass(frozen=True)
class PositionOutput:
    """The position loop's answer: the attitude + thrust the vehicle should have."""

    q_target: FloatArray  # [w, x, y, z] body FRD -> NED
    euler_target_rad: Vec3  # roll, pitch, yaw
    thrust_norm: float
    acc_cmd_ned_m_s2: FloatArray
    p_hat_ned_m_s2: FloatArray  # the acceleration disturbance estimate used
    source: str
    compute_us: float
    ref_pos_ned_m: FloatArray


@dataclass(frozen=True)
class AttitudeOutput:
    rates_frd_rad_s: FloatArray | None  # None: let the autopilot track q_target itself
    thrust_norm: float
    source: str


def _stats(ctrl: Controller | None) -> dict[str, Any]:
    if isinstance(ctrl, ExperienceController):
        s = ctrl.stats
        return {
            "size": int(s.size),
            "hits": int(s.hits),
            "misses": int(s.misses),
            "qp_solves": int(s.qp_solves),
            "intermediate": int(s.intermediate),
            "fallback": int(s.fallback),
            "received_shared": int(getattr(s, "received_shared", 0)),
            "candidates": int(s.candidates),
        }
    return {}


@dataclass
class _Observation:
    t_s: float  # when the velocity was measured (vehicle time of its position sample)
    vel_ned_m_s: FloatArray
    acc_achieved_ned_m_s2: FloatArray


@dataclass
class Cascade:
    """Both loops' numerics for one vehicle, built from the service config."""

    position_cfg: PositionControlConfig
    attitude_cfg: AttitudeControlConfig
    estimator_cfg: EstimatorConfig
    loop_period_s: float = 0.01  # the position loop's period: the estimator's filter step
    # False: a miss applies the intermediate controller and queues θ for a worker
    # (miss_solver.MissSolver) instead of solving the full QP inside the tick
    learn_on_miss: bool = True
    _history: deque[_Observation] = field(default_factory=lambda: deque(maxlen=64))
    _hold_pos: FloatArray | None = None
    _last_thrust_norm: float = math.nan
    yaw_target_rad: float | None = None  # a live reference's heading; None: position.yaw_deg

    def __post_init__(self) -> None:
        pc, ac = self.position_cfg, self.attitude_cfg
        self.position_dt_s = pc.dt_s
        self.position_horizon = pc.horizon
        self.pos_model = position_model_lagged(pc.dt_s, pc.tau_acc_s)
        # a[k+1] = alpha a[k] + (1 - alpha) u[k] per axis: what the feedforward inverts
        self._acc_alpha = np.exp(-pc.dt_s / np.array(pc.tau_acc_s, dtype=np.float64))
        self._one_minus_alpha = 1.0 - self._acc_alpha
        # the tick's scratch arrays (not kept by anything the tick returns)
        self._z_stages = np.empty((pc.horizon + 1, 3))  # estimator query: v of x_0..x_N
        self._x0 = np.empty(9)  # [p_ned, v_ned, a_ned]
        self.acc_limits = acceleration_limits(
            math.radians(pc.max_tilt_deg),
            pc.min_thrust_norm,
            pc.max_thrust_norm,
            pc.hover_thrust_norm,
        )
        box = self.acc_limits
        # the disturbance estimate is not a command: it is bounded only by what the vehicle
        # could ever compensate (clipping it to the command limits hid strong wind)
        self._d_max = GRAVITY_M_S2 * pc.max_thrust_norm / pc.hover_thrust_norm
        inf3 = np.full(3, math.inf)
        vmax = np.array(pc.max_vel_m_s, dtype=np.float64)
        pmin = inf3 * -1 if pc.geofence_min_ned_m is None else np.array(pc.geofence_min_ned_m)
        pmax = inf3 if pc.geofence_max_ned_m is None else np.array(pc.geofence_max_ned_m)
        self.pos_problem = MpcProblem(
            self.pos_model,
            horizon=pc.horizon,
            Q=np.concatenate([pc.q_pos, pc.q_vel, pc.q_acc]),
            R=np.array(pc.r_acc, dtype=np.float64),
            x_min=np.concatenate([pmin, -vmax, -inf3]),
            x_max=np.concatenate([pmax, vmax, inf3]),
            u_min=box.u_min,
            u_max=box.u_max,
            u_poly=(box.P, box.p),
        )
        self.position: Controller
        if pc.controller == "epc":
            epc = ExperienceController(
                self.pos_problem, max_size=pc.library_size, learn_on_miss=self.learn_on_miss
            )
            epc.max_checks = epc.checks_within(pc.query_budget_us)
            self.position = epc
        elif pc.controller == "mpc":
            self.position = MpcController(self.pos_problem)
        else:
            self.position = PdController(self.pos_problem, kp=pc.pd_kp, kd=pc.pd_kd)
        att_model = attitude_model(ac.dt_s, ac.rate_time_constant_s)
        rmax = np.array(ac.max_rate_rad_s, dtype=np.float64)
        self.att_problem = MpcProblem(
            att_model,
            horizon=ac.horizon,
            Q=np.concatenate([ac.q_angle, ac.q_rate]),
            R=np.array(ac.r_rate, dtype=np.float64),
            u_min=-rmax,
            u_max=rmax,
        )
        self.attitude = ExperienceController(
            self.att_problem, max_size=ac.library_size, learn_on_miss=self.learn_on_miss
        )
        self.attitude.max_checks = self.attitude.checks_within(ac.query_budget_us)
        ec = self.estimator_cfg
        self.estimator = make_estimator(
            ec.kind,
            3,
            3,
            PerturbationConfig(
                lwpr=replace(ec.lwpr, dt_s=self.loop_period_s),
                kf=replace(ec.kf, dt_s=self.loop_period_s),
            ),
        )
        self._estimator_key = f"estimator.{self.estimator_cfg.kind}"
        # (9, 3): how an acceleration disturbance enters one prediction step
        self._e_dist = velocity_disturbance_input(self.pos_model)

    # -- position loop ------------------------------------------------------------------

    def hold_position(self, pos_ned_m: FloatArray) -> None:
        self._hold_pos = np.asarray(pos_ned_m, dtype=np.float64).copy()

    def hold_refs(self, state: VehicleState) -> FloatArray:
        """References that hold the hold point (or the current position) at rest."""
        if self._hold_pos is None:
            self._hold_pos = state.pos_ned_m.copy()
        row = np.concatenate([self._hold_pos, np.zeros(6)])
        out: FloatArray = np.tile(row, (self.position_horizon, 1))
        return out

    def _observe(self, state: VehicleState, achieved: FloatArray) -> None:
        """Feed the estimator the disturbance measured over the last prediction step;
        ``achieved`` (3,): :meth:`achieved_acceleration` at this state.

        Velocities are taken on their own sample times, once per new position sample: a
        velocity repeated while its stream lags (or stops, as when an estimator drops out)
        would read as a disturbance cancelling the whole commanded acceleration. A sample
        older than a prediction step clears the history: nothing is learnt across a gap.
        """
        if state.position_age_s > self.position_dt_s:
            self._history.clear()
            return
        t_vel = state.time_s - state.position_age_s
        if self._history and t_vel <= self._history[-1].t_s + 1e-9:
            return  # no new velocity sample since the last observation
        if not math.isnan(self._last_thrust_norm):
            # ``achieved``: the measured attitude with the last commanded thrust
            self._history.append(_Observation(t_vel, state.vel_ned_m_s.copy(), achieved))
        if len(self._history) < 2:
            return
        newest = self._history[-1]
        oldest = None
        for obs in self._history:  # the oldest sample still within one prediction step
            if newest.t_s - obs.t_s <= self.position_dt_s + 1e-9:
                oldest = obs
                break
        if oldest is None or newest.t_s - oldest.t_s < 0.5 * self.position_dt_s:
            return
        span = newest.t_s - oldest.t_s
        window = [
            o.acc_achieved_ned_m_s2 for o in self._history if oldest.t_s <= o.t_s < newest.t_s
        ]
        d_meas = (newest.vel_ned_m_s - oldest.vel_ned_m_s) / span - np.mean(window, axis=0)
        # d_meas is the mean disturbance over the window: pair it with the mean velocity
        # over the same window (drag at the window's start would be a 1/2-window lag)
        z = np.mean([o.vel_ned_m_s for o in self._history if o.t_s >= oldest.t_s], axis=0)
        self.estimator.observe(z, d_meas)

    def feedforward(self, refs: FloatArray) -> FloatArray:
        """(N, 3) commands that make the model's lagged acceleration follow the reference's.

        Exact inverse of ``a[k+1] = alpha a[k] + (1 - alpha) u[k]`` along the reference
        accelerations ``refs[:, 6:9]`` (a_1..a_N); a_0, the reference acceleration now, is
        extrapolated linearly from a_1 and a_2 (exact for a piecewise-linear reference).
        """
        a_ref = refs[:, 6:9]
        a_now = 2.0 * a_ref[0] - a_ref[1] if len(a_ref) >= 2 else a_ref[0]
        return self._lag_inverse(np.vstack([a_now, a_ref]))

    def _lag_inverse(self, a: FloatArray) -> FloatArray:
        """(N, 3) commands that make the lagged acceleration follow ``a`` (N+1, 3), the
        values at x_0..x_N: ``u_k = (a_{k+1} - alpha a_k) / (1 - alpha)``."""
        out: FloatArray = (a[1:] - self._acc_alpha * a[:-1]) / self._one_minus_alpha
        return out

    def achieved_acceleration(self, state: VehicleState) -> FloatArray:
        """The acceleration (NED, gravity compensated) the measured attitude produces with the
        last commanded thrust: the model's ``a`` state now."""
        thrust = self._last_thrust_norm
        if math.isnan(thrust):
            thrust = self.position_cfg.hover_thrust_norm
        roll, pitch, yaw = state.euler_rad
        return attitude_to_accel(
            AttitudeThrust(roll, pitch, yaw, thrust), self.position_cfg.hover_thrust_norm
        )

    def position_tick(
        self, state: VehicleState, refs: FloatArray, *, learn: bool = True
    ) -> PositionOutput:
        """One position-loop tick; ``refs`` (N, 9) rows [p_ned, v_ned, a_ned] for x[1..N].

        ``learn``: the vehicle is flying our commands, so the measured disturbance is real
        (before offboard is confirmed, our thrust is not what flies and must not be learned).
        """
        t0 = time.perf_counter()
        achieved = self.achieved_acceleration(state)
        if learn:
            self._observe(state, achieved)
        else:
            self._history.clear()
        d_max = self._d_max
        if isinstance(self.position, PdController):
            # thesis A.1: PD takes its acceleration feedforward from the reference horizon
            # itself; the nominal input only cancels the disturbance
            d_hat = np.clip(self.estimator.estimate(state.vel_ned_m_s), -d_max, d_max)
            u_p = np.broadcast_to(-d_hat, (self.position_horizon, 3))
        else:
            # the disturbance at each stage's reference velocity, as the estimator knows it
            # (LWPR's d(v); zero change for the KF observer): the nominal input that keeps the
            # lagged acceleration on a_ref - d along the horizon, not only on a_ref - d_hat.
            # One prediction pass gives both the estimate at v (row 0) and its variation.
            z_stages = self._z_stages
            z_stages[0] = state.vel_ned_m_s
            z_stages[1:] = refs[:, 3:6]  # v of x_0..x_N
            p_hat, d_var = self.estimator.estimate_along(z_stages)
            d_hat = np.clip(p_hat, -d_max, d_max)
            d_var = np.clip(d_hat + d_var, -d_max, d_max) - d_hat
            u_p = self.feedforward(refs) - d_hat - self._lag_inverse(d_var)
        x0 = self._x0
        x0[0:3] = state.pos_ned_m
        x0[3:6] = state.vel_ned_m_s
        x0[6:9] = achieved
        decision: Decision = self.position.step(
            x0, refs, u_p, perturbation=self._e_dist @ d_hat
        )
        acc = limit_tilt(np.asarray(decision.u, dtype=np.float64), self.acc_limits)
        out = self._attitude_target(acc, d_hat, decision.source, refs, t0)
        self._last_thrust_norm = out.thrust_norm
        return out

    def _attitude_target(
        self, acc: FloatArray, d_hat: FloatArray, source: str, refs: FloatArray, t0: float
    ) -> PositionOutput:
        pc = self.position_cfg
        yaw = math.radians(pc.yaw_deg) if self.yaw_target_rad is None else self.yaw_target_rad
        att = accel_to_attitude(acc, yaw, pc.hover_thrust_norm)
        thrust = min(max(att.thrust_norm, pc.min_thrust_norm), pc.max_thrust_norm)
        return PositionOutput(
            q_target=frames.euler_to_quat(att.roll_rad, att.pitch_rad, att.yaw_rad),
            euler_target_rad=(att.roll_rad, att.pitch_rad, att.yaw_rad),
            thrust_norm=thrust,
            acc_cmd_ned_m_s2=acc,
            p_hat_ned_m_s2=d_hat,
            source=source,
            compute_us=(time.perf_counter() - t0) * 1e6,
            ref_pos_ned_m=refs[0, :3].copy(),
        )

    def hover(self, state: VehicleState) -> PositionOutput:
        """The safe command when the position loop cannot answer: level, hover thrust."""
        pc = self.position_cfg
        yaw = state.yaw_rad
        self._last_thrust_norm = pc.hover_thrust_norm
        return PositionOutput(
            q_target=frames.euler_to_quat(0.0, 0.0, yaw),
            euler_target_rad=(0.0, 0.0, yaw),
            thrust_norm=pc.hover_thrust_norm,
            acc_cmd_ned_m_s2=np.zeros(3),
            p_hat_ned_m_s2=np.zeros(3),
            source="fallback",
            compute_us=0.0,
            ref_pos_ned_m=state.pos_ned_m.copy(),
        )

    # -- attitude loop ------------------------------------------------------------------

    def rates_trusted(self, state: VehicleState, target: PositionOutput) -> bool:
        """Whether the attitude is where the body-rate EPC's hover linearisation holds: tilt
        and distance to the attitude target within ``rates_max_tilt_deg`` /
        ``rates_max_error_deg``. Outside, the attitude goes to the autopilot's own loop."""
        acfg = self.attitude_cfg
        tilt = frames.tilt_deg(state.q_ned_frd)
        error = frames.angle_between_deg(state.q_ned_frd, target.q_target)
        return tilt <= acfg.rates_max_tilt_deg and error <= acfg.rates_max_error_deg

    def _attitude_refs(
        self, state: VehicleState, target: PositionOutput
    ) -> tuple[FloatArray, FloatArray]:
        roll, pitch, yaw = state.euler_rad
        troll, tpitch, tyaw = target.euler_target_rad
        # take the short way round in yaw: the reference is expressed next to the current yaw
        tyaw = yaw + frames.wrap_pi(tyaw - yaw)
        x0 = np.array([roll, pitch, yaw, *state.rate_frd_rad_s])
        row = np.array([troll, tpitch, tyaw, 0.0, 0.0, 0.0])
        return x0, np.tile(row, (self.attitude_cfg.horizon, 1))

    def attitude_tick(self, state: VehicleState, target: PositionOutput) -> AttitudeOutput:
        x0, refs = self._attitude_refs(state, target)
        d = self.attitude.step(x0, refs)
        return AttitudeOutput(np.asarray(d.u, dtype=np.float64), target.thrust_norm, d.source)

    def attitude_fallback(self, state: VehicleState, target: PositionOutput) -> AttitudeOutput:
        x0, refs = self._attitude_refs(state, target)
        rmax = np.array(self.attitude_cfg.max_rate_rad_s)
        rates = np.clip(self.attitude_cfg.fallback_gain_1_s * (refs[0, :3] - x0[:3]), -rmax, rmax)
        return AttitudeOutput(rates, target.thrust_norm, "fallback")

    def warm_up(self) -> float:
        """Run both ticks of a scratch cascade with this configuration at hover, so every
        compiled kernel (numba) is compiled or loaded from its cache now, not inside the
        first control tick. Leaves this cascade untouched; returns the seconds it took."""
        t0 = time.perf_counter()
        if self.estimator_cfg.kind == "lwpr":
            lwpr.warm_up()  # every LWPR kernel, whatever the few scratch ticks exercise
        kernels.warm_up()  # the library scan: an empty scratch library never runs it
        trajectories.warm_up()  # the reference horizon the service hands in
        scratch = Cascade(
            self.position_cfg, self.attitude_cfg, self.estimator_cfg, self.loop_period_s
        )
        for k in range(3):
            state = VehicleState(
                time_s=k * self.loop_period_s,
                pos_ned_m=np.array([0.0, 0.0, -2.5]),
                vel_ned_m_s=np.zeros(3),
                q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]),
                rate_frd_rad_s=np.zeros(3),
                position_age_s=0.0,
                attitude_age_s=0.0,
            )
            target = scratch.position_tick(state, scratch.hold_refs(state), learn=True)
            scratch.attitude_tick(state, target)
        return time.perf_counter() - t0

    # -- experience on disk ---------------------------------------------------------------

    def experience_controllers(self) -> list[tuple[str, ExperienceController]]:
        """(name, controller) of each EPC problem: what is stored and what the fleet shares.
        The caller owns ``pop_new_entries`` (the service publishes them, or discards them
        when not sharing)."""
        out = [("attitude", self.attitude)]
        if isinstance(self.position, ExperienceController):
            out.insert(0, ("position", self.position))
        return out

    def store_snapshot(self) -> LibrarySnapshot:
        """Every controller (importance, uses, transitions) and the estimator, copied now.

        Take it on the thread that runs the loops (the library is not thread-safe); the copy
        can then be saved (:meth:`LibraryStore.save_snapshot`) from a worker thread while the
        loops fly on.
        """
        parts: dict[str, SignatureSnapshot] = {}
        for _name, ctrl in self.experience_controllers():
            entries = ctrl.export_library()
            sets = [e.active_set for e in entries]
            parts[ctrl.problem.signature()] = SignatureSnapshot(
                tuple(_stored(e) for e in entries),
                tuple(
                    Transition(sets[a], sets[b], n)
                    for (a, b), n in ctrl.export_transitions().items()
                ),
            )
        # the estimator is kept under the position problem's signature (also for PD / MPC)
        pos_sig = self.pos_problem.signature()
        parts[pos_sig] = replace(
            parts.get(pos_sig, SignatureSnapshot()),
            models={self._estimator_key: self.estimator.to_bytes()},
        )
        return LibrarySnapshot(parts)

    def save_to(self, store: LibraryStore) -> None:
        """Snapshot and save at once (on the loops' thread, e.g. at shutdown)."""
        store.save_snapshot(self.store_snapshot())

    def load_from(self, store: LibraryStore) -> dict[str, int]:
        """Load the prior library (thesis M_prior) and estimator; returns counts per part.

        Every stored controller is re-validated against this problem; one that fails is
        skipped with a log line, never applied (and, as always, only KKT-checked use).
        """
        loaded: dict[str, int] = {}
        for name, ctrl in self.experience_controllers():
            sig = ctrl.problem.signature()
            stored = store.load_controllers(sig)[: ctrl.max_size]
            entries = [LibraryEntry(e.active_set, e.importance, e.uses, e.origin) for e in stored]
            index = {e.active_set: i for i, e in enumerate(entries)}
            transitions = {
                (index[a], index[b]): n
                for (a, b), n in store.load_transitions(sig).items()
                if a in index and b in index and n >= 1
            }
            try:
                loaded[name] = ctrl.import_entries(entries, "prior", transitions=transitions)
            except ValueError as exc:
                log.warning("stored %s library: %s; importing entry by entry", name, exc)
                loaded[name] = 0
                for e in entries:
                    try:
                        loaded[name] += ctrl.import_entries([e], "prior")
                    except ValueError as exc_one:
                        log.warning(
                            "stored %s controller %s skipped: %s", name, e.active_set, exc_one
                        )
        blob = store.load_model(self._estimator_key, self.pos_problem.signature())
        if blob is not None:
            try:
                self.estimator.load_bytes(blob)
                loaded["estimator"] = 1
            except ValueError as exc:
                log.warning("stored estimator ignored: %s", exc)
        return loaded

    def library_stats(self) -> dict[str, Any]:
        return {"position": _stats(self.position), "attitude": _stats(self.attitude)}


def _stored(e: LibraryEntry) -> StoredController:
    """The store's row of a library entry; its origin travels with it (a promoted fleet
    candidate stays ``shared:<vehicle>``, never becomes this vehicle's "solved")."""
    return StoredController(
        tuple(int(i) for i in e.active_set), float(e.importance), int(e.uses),
        e.origin or "solved",
    )  # fmt: skip
