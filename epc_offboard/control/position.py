"""The position loop (100 Hz): one tick from the vehicle state and the reference horizon to
the attitude and thrust the vehicle should have.

Pure numerics (no asyncio, no MAVLink). :meth:`PositionLoop.position_tick`:

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
4. control: EPC (or PD / MPC-every-tick) over the reference horizon -> ``a_cmd``, from the
   state predicted over the command dead time with the commands in flight, on the reference
   window that starts there (:mod:`~epc_offboard.control.dead_time`);
5. map: ``a_cmd`` -> roll, pitch, yaw, thrust (thesis eq. 3.13, exact inverse, NED).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from epc_offboard.common import frames, jit
from epc_offboard.common.airframe import Airframe
from epc_offboard.common.frames import GRAVITY_M_S2, FloatArray
from epc_offboard.control.baselines import MpcController, PdController
from epc_offboard.control.dead_time import (
    DEFAULT_COMMAND_DEAD_TIME_S,
    DeadTimePredictor,
    check_span_s,
    default_command_dead_time_s,
)
from epc_offboard.control.decision import Controller, Decision
from epc_offboard.control.epc import budgeted_controller
from epc_offboard.control.kernels import (
    dead_time_constants,
    disturbance_plan,
    filtered_plan,
    lwpr_plan,
    plan_step,
    tilt_reach,
)
from epc_offboard.control.models import (
    LAG_ACC_STATES,
    AccelLimits,
    accel_to_attitude,
    acceleration_limits,
    attitude_to_axis_xyz,
    limit_tilt,
    position_model_lagged,
    velocity_disturbance_input,
)
from epc_offboard.control.perturbation import (
    EstimatorConfig,
    KalmanPerturbation,
    LwprPerturbation,
    PerturbationConfig,
    make_estimator,
)
from epc_offboard.control.qp import MpcProblem
from epc_offboard.control.state_filter import StateFilter, StateFilterConfig
from epc_offboard.control.types import PositionOutput, ReferenceHorizon, VehicleState

Vec3 = tuple[float, float, float]

_F64 = np.dtype(np.float64)  # (an array's dtype is this object: the compiled calls' check)

# below this largest reach-to-slack ratio limit_tilt scales nothing (see _limit_tilt)
_TILT_EXACT_BELOW = 1.0 - 1e-6


@dataclass(frozen=True)
class PdGains:
    """``[position.pd]``: the pd controller's gains, per NED axis."""

    kp_1_s2: Vec3 = (6.0, 6.0, 8.0)  # acceleration per metre of position error
    kd_1_s: Vec3 = (4.5, 4.5, 5.0)  # acceleration per m/s of velocity error

    def __post_init__(self) -> None:
        if any(k < 0.0 for k in (*self.kp_1_s2, *self.kd_1_s)):
            raise ValueError("kp_1_s2 and kd_1_s must be >= 0")


@dataclass(frozen=True)
class LibraryBudget:
    """``[position.library]``: the EPC library's size and the cost of one query."""

    size: int = 400
    # a library query's worst-case cost: bounds the candidates a miss checks (the most
    # likely first: the last controller, its successors, then by importance). 3000 us of the
    # worst-case model is ~190 position maps (a check usually exits within a few rows, at a
    # fraction of that); 400 us (25 maps) left a saved library's controllers unchecked: a
    # second zig-zag flight missed 122 ticks instead of 42, and a miss costs more than the
    # checks it saves (the intermediate QP on the loop and a solve in the worker)
    query_budget_us: float = 3000.0

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError(f"size must be >= 1, got {self.size}")
        if not self.query_budget_us > 0.0:
            raise ValueError(f"query_budget_us must be > 0, got {self.query_budget_us}")


@dataclass(frozen=True)
class PositionControlConfig:
    """``[position]``: the controller, its horizon, weights, model and entry; the pd gains
    and the library budget in their own tables. The airframe's envelope (tilt and thrust
    limits, hover thrust) is not here: it comes from the vehicle file
    (:class:`~epc_offboard.common.airframe.Airframe`)."""

    # px4: a baseline, the autopilot's own position controller flies the reference
    # (SET_POSITION_TARGET_LOCAL_NED with position, velocity and acceleration)
    controller: Literal["epc", "pd", "mpc", "px4"] = "epc"
    horizon: int = 20
    dt_s: float = 0.05  # prediction step, separate from the loop period
    # Four times the position weight (twice the position gain) of (20, 20, 30) / (3, 3, 3):
    # what was left of the tracking error was a steady offset, a residual of the
    # disturbance model held off by the position gain, not the cascade's lag (issue 24).
    # Flown with the jerk bound below: without it the heavier weights rode a velocity bound
    # in a limit cycle (see max_jerk_m_s3)
    q_pos: Vec3 = (80.0, 80.0, 120.0)
    q_vel: Vec3 = (6.0, 6.0, 6.0)
    q_acc: Vec3 = (0.0, 0.0, 0.0)  # weight on the achieved-acceleration error
    # inner-loop lag from commanded to achieved acceleration, first order, per NED axis:
    # horizontally the attitude loop's response (identified on the bundled SITL from
    # commanded vs ground-truth acceleration), vertically the motors' (thrust is direct)
    tau_acc_s: Vec3 = (0.12, 0.12, 0.03)
    # dead time (s) before that lag, from a command sent to the acceleration it starts to
    # produce, on every axis (a quaternion setpoint carries its thrust): the QP starts from
    # the state predicted over it with the commands in flight, on the reference as it will
    # be then (control/dead_time.py). Unset: the measured one of the autopilot and attitude
    # mode flown (PX4 quaternion 0.15 s, body rates 0.05; DEFAULT_COMMAND_DEAD_TIME_S)
    command_dead_time_s: float | None = None
    # How old the state estimate already is when it arrives, beyond what its time stamp
    # shows (s): an estimator's output lag and the link's delay, stamped as current (the
    # Neural-Fly plant's 15 ms). x0 is carried over it with the commands flown meanwhile
    # (with the command dead time), the reference window is not shifted by it
    state_latency_s: float = 0.0
    # [position.state_filter]: the state estimate's error the QP's initial state is fused
    # against (control/state_filter.py); unset, the measured state as is
    state_filter: StateFilterConfig = field(default_factory=StateFilterConfig)
    r_acc: Vec3 = (0.3, 0.3, 0.3)
    max_vel_m_s: Vec3 = (3.8, 3.8, 2.0)  # state constraint |v_i| <= max (thesis zig-zag: 3.8)
    # The QP bounds the predicted velocity by max_vel_m_s less this (constraint tightening,
    # as robust MPC does): the true velocity differs from the prediction by the estimate's
    # noise and the disturbance model's residual, and a plan riding the bound exactly (the
    # heavy position weights chase a lag at full speed) overshot it by that: 3.814 m/s
    # against 3.8 on the zig-zag (seed 1; main's weights 3.803), 0.01-0.02 m/s
    vel_margin_m_s: float = 0.05
    # The horizontal jerk a plan may ask of the lagged acceleration, |u - a| <= jerk * tau
    # at every stage (0: unbounded). The lag model holds while the tilt rate it implies,
    # about jerk / g, is one the attitude loop follows; a plan that swings the command
    # across the tilt range (riding a velocity bound with the heavy position weights: -8
    # to +10 m/s^2 within 0.2 s) saturates the body rates (4 rad/s: 39 m/s^3), the vehicle
    # lags the model by 15-20 deg of tilt, overshoots, and the next plan swings back: a
    # limit cycle through the bound (3.11 m/s against 3.0 on the bounded zig-zag). 20 m/s^3
    # is half the rate limit's jerk: 0 violations; 40 still overshot (3.04 m/s).
    max_jerk_m_s3: float = 20.0
    # ... on the first jerk_stages stages (0.2 s): the plan's near part, which the first
    # command is flown from. On all 20 the rows' combinations multiplied the active sets
    # (a second bounded zig-zag from the first's library still missed 240 ticks of 290; 4
    # stages: 119 of 253), with the same bound kept (0 violations, 2.81 m/s)
    jerk_stages: int = 4
    geofence_min_ned_m: Vec3 | None = None  # optional position box
    geofence_max_ned_m: Vec3 | None = None
    yaw_deg: float = 0.0  # heading held while tracking
    pd: PdGains = field(default_factory=PdGains)
    library: LibraryBudget = field(default_factory=LibraryBudget)
    # entry (and every re-entry after a failsafe): the commanded acceleration starts from
    # the one the vehicle flies and changes by at most entry_jerk_m_s3 (its norm) until
    # entry_ramp_s after the autopilot is confirmed to fly ours; 6 m/s^3 is ~35 deg/s of tilt
    entry_ramp_s: float = 1.0
    entry_jerk_m_s3: float = 6.0
    # and at most this far from the acceleration that holds against the estimated
    # disturbance: a re-entry braking a drift after a hold that let it go (2.5 m/s^2 is
    # 14 deg of tilt beyond the wind's)
    entry_max_acc_m_s2: float = 2.5
    # vertically, within this: a calm entry holds its altitude (the QP may otherwise buy
    # tilt authority with thrust and climb with it: 0.36 m on an ArduCopter re-entry)
    entry_max_vertical_acc_m_s2: float = 0.6
    # The thrust is sized for the tilt the vehicle flies (measured), not the target's, so
    # that its vertical part is the commanded one while the tilt lags the target: sized for
    # the target's, a tilt-up into 6 m/s wind lagging 3-6 deg climbed 0.15 m (ArduCopter
    # re-entry; its own angle boost does the same for its own targets). The thrust stays
    # within this factor of the target's (and 1/factor); 1.0: the target's tilt alone.
    thrust_tilt_ratio_max: float = 1.4
    # The thrust's bound |f| <= f_max on the commanded acceleration as eight planes
    # (control/models.py acceleration_limits), so that the vertical specific thrust reaches
    # g + (f_max - g) / 2 while the vehicle tilts less than its limit, instead of the cap
    # f_max cos(max tilt) at any tilt: the Neural-Fly scenario's strong wind (issue 24)
    thrust_facets: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.thrust_tilt_ratio_max) and self.thrust_tilt_ratio_max >= 1.0):
            raise ValueError(
                f"thrust_tilt_ratio_max must be >= 1, got {self.thrust_tilt_ratio_max}"
            )
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")
        if self.dt_s <= 0.0:
            raise ValueError(f"dt_s must be > 0, got {self.dt_s}")
        if any(v <= 0.0 for v in self.max_vel_m_s):
            raise ValueError(f"max_vel_m_s must be > 0, got {self.max_vel_m_s}")
        if not (math.isfinite(self.vel_margin_m_s)
                and 0.0 <= self.vel_margin_m_s < min(self.max_vel_m_s)):  # fmt: skip
            raise ValueError(f"vel_margin_m_s must be >= 0 and below every max_vel_m_s, "
                             f"got {self.vel_margin_m_s}")
        if not (math.isfinite(self.max_jerk_m_s3) and self.max_jerk_m_s3 >= 0.0):
            raise ValueError(f"max_jerk_m_s3 must be >= 0, got {self.max_jerk_m_s3}")
        if self.jerk_stages < 1:
            raise ValueError(f"jerk_stages must be >= 1, got {self.jerk_stages}")
        if any(not t > 0.0 for t in self.tau_acc_s):
            raise ValueError(f"tau_acc_s must be > 0, got {self.tau_acc_s}")
        if self.command_dead_time_s is not None:
            check_span_s("command_dead_time_s", self.command_dead_time_s)
        check_span_s("state_latency_s", self.state_latency_s)
        if any(q < 0.0 for q in (*self.q_pos, *self.q_vel, *self.q_acc)):
            raise ValueError("q_pos, q_vel and q_acc must be >= 0")
        if not (math.isfinite(self.entry_ramp_s) and self.entry_ramp_s >= 0.0):
            raise ValueError(f"entry_ramp_s must be >= 0, got {self.entry_ramp_s}")
        if not (math.isfinite(self.entry_jerk_m_s3) and self.entry_jerk_m_s3 > 0.0):
            raise ValueError(f"entry_jerk_m_s3 must be > 0, got {self.entry_jerk_m_s3}")
        if not (math.isfinite(self.entry_max_acc_m_s2) and self.entry_max_acc_m_s2 > 0.0):
            raise ValueError(f"entry_max_acc_m_s2 must be > 0, got {self.entry_max_acc_m_s2}")
        if not (
            math.isfinite(self.entry_max_vertical_acc_m_s2)
            and self.entry_max_vertical_acc_m_s2 > 0.0
        ):
            raise ValueError(
                f"entry_max_vertical_acc_m_s2 must be > 0, got {self.entry_max_vertical_acc_m_s2}"
            )

    @property
    def reference_steps(self) -> int:
        """The stages ahead a reference horizon must carry: the QP's horizon past the
        longest command dead time this configuration may fly (the window starts there)."""
        dead = self.command_dead_time_s
        if dead is None:
            dead = max(DEFAULT_COMMAND_DEAD_TIME_S.values())
        return self.horizon + math.ceil(dead / self.dt_s - 1e-9)

    @property
    def yaw_rad(self) -> float:
        """The heading held while tracking a reference that has none of its own (rad)."""
        return math.radians(self.yaw_deg)


# One velocity sample of the estimator's window, plain floats (the tick allocates no object
# per sample): (t_s: when the velocity was measured, the vehicle time of its position
# sample; vel_ned_m_s (3); thrust_axis_ned (3): body z (FRD) in NED, the specific thrust is
# -f * this; f: the specific thrust flown (m/s^2), NaN while the autopilot flies its own).
_Observation = tuple[float, float, float, float, float, float, float, float]


def _pairwise_sum(values: list[float]) -> float:
    """The sum numpy takes of a 1-D float64 array (pairwise: eight accumulators from eight
    values on, in blocks below 128), so that a mean over a few Python floats is numpy's to
    the last bit (the lockstep flights stay identical) without building an array."""
    n = len(values)
    if n < 8:
        res = 0.0
        for v in values:
            res += v
        return res
    if n > 128:  # numpy splits larger blocks in halves (not met: the window holds <= 64)
        half = (n // 2) - (n // 2) % 8
        return _pairwise_sum(values[:half]) + _pairwise_sum(values[half:])
    r = values[:8]
    i = 8
    while i < n - n % 8:
        for j in range(8):
            r[j] += values[i + j]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += values[i]
        i += 1
    return res


def _vec3s(a: Any, b: Any, c: Any) -> bool:
    """Each a (3,) C-contiguous float64 array: what a compiled entry point takes as one
    (the state's vectors; the tick's own, ``achieved`` and the last ``d_hat``, are made so).
    One call, no generator (each of its steps is a Python-level call)."""
    return (type(a) is np.ndarray and type(b) is np.ndarray and type(c) is np.ndarray
            and a.dtype is _F64 and b.dtype is _F64 and c.dtype is _F64
            and a.shape == (3,) and b.shape == (3,) and c.shape == (3,)
            and a.flags.c_contiguous and b.flags.c_contiguous
            and c.flags.c_contiguous)  # fmt: skip


def position_problem(cfg: PositionControlConfig, limits: AccelLimits) -> MpcProblem:
    """The position QP: the lagged model over ``cfg.horizon`` steps of ``cfg.dt_s``, the
    velocity bounds (tightened by ``cfg.vel_margin_m_s``) and the geofence as state
    constraints, the jerk bound as lead rows, the tilt and thrust limits as
    ``limits`` on the commanded acceleration."""
    inf3 = np.full(3, math.inf)
    vmax = np.array(cfg.max_vel_m_s, dtype=np.float64) - cfg.vel_margin_m_s
    pmin = inf3 * -1 if cfg.geofence_min_ned_m is None else np.array(cfg.geofence_min_ned_m)
    pmax = inf3 if cfg.geofence_max_ned_m is None else np.array(cfg.geofence_max_ned_m)
    return MpcProblem(
        position_model_lagged(cfg.dt_s, cfg.tau_acc_s),
        horizon=cfg.horizon,
        Q=np.concatenate([cfg.q_pos, cfg.q_vel, cfg.q_acc]),
        R=np.array(cfg.r_acc, dtype=np.float64),
        x_min=np.concatenate([pmin, -vmax, -inf3]),
        x_max=np.concatenate([pmax, vmax, inf3]),
        u_min=limits.u_min,
        u_max=limits.u_max,
        u_poly=(limits.P, limits.p),
        lead=None if cfg.max_jerk_m_s3 == 0.0 else (
            LAG_ACC_STATES,
            [cfg.max_jerk_m_s3 * cfg.tau_acc_s[0], cfg.max_jerk_m_s3 * cfg.tau_acc_s[1], math.inf],
        ),
        lead_stages=cfg.jerk_stages,
    )


@dataclass(frozen=True)
class PositionStrategy:
    """How the position loop turns the reference horizon into a command (``controller``
    in ``PositionControlConfig``): its ``controller`` (None: the px4 baseline, the
    autopilot's own position controller flies the reference and this loop computes
    nothing), and whether the nominal input ``u_p`` carries the reference's acceleration
    feedforward (the QP methods) or only cancels the disturbance (PD: thesis A.1 takes its
    feedforward from the horizon itself)."""

    controller: Controller | None
    nominal_feedforward: bool


def position_strategy(
    cfg: PositionControlConfig, problem: MpcProblem, *, learn_on_miss: bool = True
) -> PositionStrategy:
    """The strategy ``cfg.controller`` names, over ``problem``: EPC with its library budget,
    MPC solved every tick, PD with ``cfg``'s gains, or the autopilot's (px4)."""
    if cfg.controller == "epc":
        epc = budgeted_controller(
            problem, cfg.library.size, cfg.library.query_budget_us, learn_on_miss
        )
        return PositionStrategy(epc, nominal_feedforward=True)
    if cfg.controller == "mpc":
        return PositionStrategy(MpcController(problem), nominal_feedforward=True)
    if cfg.controller == "pd":
        pd = PdController(problem, kp=cfg.pd.kp_1_s2, kd=cfg.pd.kd_1_s)
        return PositionStrategy(pd, nominal_feedforward=False)
    return PositionStrategy(None, nominal_feedforward=False)


class PositionLoop:
    """The position loop's numerics for one vehicle: its QP, controller and estimator.

    ``loop_period_s``: the loop's period, the estimator's filter step. ``learn_on_miss``
    False: an EPC miss applies the intermediate controller and queues θ for a worker
    (``miss_solver.MissSolver``) instead of solving the full QP inside the tick.
    ``airframe``: the vehicle's hover thrust and its tilt and thrust limits (from its vehicle
    file; unset, the defaults of :class:`~epc_offboard.common.airframe.Airframe`).
    """

    def __init__(
        self,
        config: PositionControlConfig,
        estimator: EstimatorConfig,
        loop_period_s: float = 0.01,
        *,
        learn_on_miss: bool = True,
        airframe: Airframe | None = None,
    ) -> None:
        cfg = self.config = config
        frame = self.airframe = airframe or Airframe()
        self.estimator_cfg = estimator
        self.loop_period_s = loop_period_s
        self.acc_limits = acceleration_limits(
            math.radians(frame.max_tilt_deg),
            frame.min_thrust_norm,
            frame.max_thrust_norm,
            frame.hover_thrust_norm,
            thrust_facets=cfg.thrust_facets,
        )
        self.problem = position_problem(cfg, self.acc_limits)
        strategy = position_strategy(cfg, self.problem, learn_on_miss=learn_on_miss)
        self.controller = strategy.controller
        self._nominal_feedforward = strategy.nominal_feedforward
        filtered = PerturbationConfig(
            lwpr=replace(estimator.lwpr, dt_s=loop_period_s),
            kf=replace(estimator.kf, dt_s=loop_period_s),
        )
        self.estimator = make_estimator(estimator.kind, 3, 3, filtered)
        # [estimator.lwpr] residual_kf: the Kalman observer follows what LWPR leaves (the
        # drag slope LWPR's forgetting learns from the estimate's noise, per flight), and its
        # estimate is added to LWPR's; None: LWPR alone (or another estimator)
        self._residual: KalmanPerturbation | None = None
        if isinstance(self.estimator, LwprPerturbation) and estimator.lwpr.residual_kf:
            self._residual = KalmanPerturbation.from_config(3, 3, filtered.kf)
        # a[k+1] = alpha a[k] + (1 - alpha) u[k] per axis: what the feedforward inverts
        self.acc_alpha = np.exp(-cfg.dt_s / np.array(cfg.tau_acc_s, dtype=np.float64))
        self._one_minus_alpha = 1.0 - self.acc_alpha
        # (9, 3): how an acceleration disturbance enters one prediction step
        self._e_dist = velocity_disturbance_input(self.problem.model)
        # the disturbance estimate is not a command: it is bounded only by what the vehicle
        # could ever compensate (clipping it to the command limits hid strong wind)
        self._d_max = GRAVITY_M_S2 * frame.max_thrust_norm / frame.hover_thrust_norm
        self._history: deque[_Observation] = deque(maxlen=64)
        self._last_thrust_norm = math.nan
        # The thrust the vehicle flies: the commands through the motors' first-order lag
        # (the model's vertical tau_acc_s). Taking the command itself as flown read every
        # thrust step as a vertical disturbance until the motors caught up (a step to
        # 0.85 at hover 0.5 "measured" +6.9 m/s^2 downwards; the estimate then climbed).
        self._thrust_gain = 1.0 - math.exp(-loop_period_s / cfg.tau_acc_s[2])
        self._thrust_flown_norm = math.nan
        # The vertical disturbance assumed while the autopilot flies its own thrust, which
        # cannot be told from it (see observe); set from the autopilot's hover thrust.
        self._d_down_prior_m_s2 = 0.0
        # entry ramp (see _entry_ramp): the last acceleration sent while ramping, the
        # vehicle time the ramp ends (inf until the autopilot is confirmed to fly ours)
        self._last_tick_s = -math.inf
        self._ramp_acc: FloatArray | None = None
        self._ramp_end_s = math.inf
        # how far a vehicle flying the ramp lags behind it: the jerk over twice the slowest
        # inner-loop lag
        self._ramp_lead_m_s2 = cfg.entry_jerk_m_s3 * 2.0 * max(cfg.tau_acc_s)
        # the tick's scratch arrays (not kept by anything the tick returns)
        # estimator query: v now, the variation's origin, the reference's v at x_1..x_N
        self._z_stages = np.empty((cfg.horizon + 2, 3))
        # [p_ned, v_ned, a_ned], then the perturbation E d_hat (the compiled plan's x0)
        self._x0_perturbation = np.empty(18)
        self._x0 = self._x0_perturbation[:9]
        self._perturbation = self._x0_perturbation[9:]
        self._a_stages = np.empty((cfg.horizon + 1, 3))  # feedforward: a of x_0..x_N
        # the varying disturbance's drift of x_1..x_N (disturbance_drift); a stays 0
        self._drift = np.zeros((cfg.horizon, 9))
        # the compiled disturbance plan's outputs: the QP's nominal inputs and references
        # (read into θ by the controller's step, kept by nothing)
        self._u_p = np.empty((cfg.horizon, 3))
        # (and the compiled plan's reference window after them)
        self._refs_window = np.empty((2 * cfg.horizon, 9))
        self._refs = self._refs_window[: cfg.horizon]
        # the command dead time flown (use_attitude_path sets the measured default once the
        # autopilot and the attitude mode are known; until then the configured one, or 0)
        self._path: tuple[str, str] | None = None
        self.dead_time = self._predictor(cfg.command_dead_time_s or 0.0)
        self._state_filter = StateFilter(cfg.state_filter, loop_period_s)
        self._feed_estimator = cfg.state_filter.enabled and cfg.state_filter.feed_estimator
        # the compiled tilt check's entry point (its arguments are always (3,) float64 and
        # this problem's limits: no dispatch on their types, issue 21), or None: numpy
        lim = self.acc_limits
        self._tilt_reach = None if tilt_reach is None else jit.entry_point(
            tilt_reach, np.zeros(3), lim.u_min, lim.u_max, lim.P, lim.p, np.empty(3))
        # the disturbance estimate of the last tick: the state filter's model acceleration
        self._d_hat_last = np.zeros(3)
        # the last _limit_tilt only clipped (far inside the tilt polygon: limiting its answer
        # again is the same clip)
        self._tilt_clipped_only = False
        # the compiled filtered plan (its entry point, the filter's state, its constants)
        # and the estimator it was made for (_filtered_plan)
        self._plan: tuple[Any, FloatArray, FloatArray] | None = None
        self._plan_for: object = None
        # the LWPR query, plan and x0 in one compiled call (kernels.lwpr_plan's entry point,
        # made with the plan), its query points' and predictions' buffers
        self._lwpr_plan: Any = None
        self._lwpr_plan_for: object = None  # the LWPR model group it was made for
        # the same with θ and the EPC's check (kernels.plan_step's entry point), and the
        # controller it was made for
        self._plan_step: Any = None
        self._plan_step_for: object = None
        self._raw = np.zeros((cfg.horizon + 2, 3))
        # its constants with the dead time's (dead_time_constants), the window's lead, and
        # the predictor they are for
        self._dead: tuple[FloatArray, int, float] | None = None
        self._dead_for: object = None

    def _filtered_plan(self) -> tuple[Any, FloatArray, FloatArray] | None:
        """:func:`~epc_offboard.control.kernels.filtered_plan`'s entry point for the
        estimator flown, with its filter's state and the plan's constants, or None where
        the tick takes the general way: no numba, an estimator other than LWPR (or one
        wrapped), or LWPR with the residual observer (its estimate joins LWPR's between
        the filter and the plan)."""
        estimator = self._plan_for = self.estimator
        self._plan = self._lwpr_plan = self._dead_for = self._plan_step_for = None
        if (filtered_plan is not None and type(estimator) is LwprPerturbation
                and self._residual is None):  # fmt: skip
            filt, n = estimator.filter, self.config.horizon
            consts = np.concatenate([self.acc_alpha, self._one_minus_alpha,
                                     [filt.gain, self._d_max, self.config.dt_s]])  # fmt: skip
            kernel = jit.entry_point(filtered_plan, np.zeros((n + 2, 3)), np.zeros((n, 9)),
                                     np.empty(3), filt.state, consts, self._u_p, self._refs)
            self._plan = (kernel, filt.state, consts)
            args = estimator.prediction_args()
            if lwpr_plan is not None and args is not None:
                v3 = np.zeros(3)
                self._lwpr_plan_for = args[3]
                planned = (v3, np.zeros((n + 1, 9)), False, 0, 0.0, *args[:3],
                           self._z_stages, self._raw, v3, v3, v3, v3, 0.0, np.empty(3),
                           filt.state, consts, self._u_p, self._refs_window,
                           self._x0_perturbation, np.zeros((1, 3)), 0)  # fmt: skip
                self._lwpr_plan = jit.entry_point(lwpr_plan, *planned)
                # with θ and the controller's check (its arguments' types are the
                # controller's: made for the one flown now, the tick checks it is)
                check = None if self.controller is None else self.controller.check_args()
                if plan_step is not None and check is not None:
                    self._plan_step = jit.entry_point(plan_step, *planned, *check)
                    self._plan_step_for = self.controller
        return self._plan

    def _dead_args(self, consts: FloatArray) -> tuple[FloatArray, int, float]:
        """The compiled plan's arguments for the dead time flown: the plan's ``consts``,
        the dead time's matrices and the disturbance's input flat
        (``kernels.dead_time_constants``), and the window's lead (made again when the
        predictor or the plan is replaced)."""
        dead_time = self._dead_for = self.dead_time
        self._dead = (dead_time_constants(consts, *dead_time.matrices(), self._e_dist),
                      *dead_time.lead(self.config.dt_s))  # fmt: skip
        return self._dead

    def use_attitude_path(self, autopilot: str, attitude_mode: str) -> None:
        """Fly the command dead time of ``autopilot`` ("px4", "ardupilot") in
        ``attitude_mode`` ("epc": body rates, "autopilot": quaternion), unless the config
        sets one (the service calls it at start and when the autopilot's dialect is
        adopted)."""
        path = (autopilot, attitude_mode)
        if path == self._path:
            return
        self._path = path
        dead = self.config.command_dead_time_s
        if dead is None:
            dead = default_command_dead_time_s(autopilot, attitude_mode)
        predictor = self._predictor(dead)
        if (predictor.steps, predictor.dead_time_s) != (self.dead_time.steps,
                                                        self.dead_time.dead_time_s):
            self.dead_time = predictor

    def _predictor(self, dead_time_s: float) -> DeadTimePredictor:
        """The predictor over ``dead_time_s`` and the configured state latency."""
        cfg = self.config
        return DeadTimePredictor(cfg.tau_acc_s, self.loop_period_s, dead_time_s,
                                 cfg.state_latency_s)  # fmt: skip

    def hold(self, pos_ned_m: FloatArray) -> ReferenceHorizon:
        """At rest at ``pos_ned_m`` (3,) m, at the configured heading, over the stages a
        reference carries (:attr:`PositionControlConfig.reference_steps`)."""
        cfg = self.config
        return ReferenceHorizon.hold(pos_ned_m, cfg.yaw_rad, cfg.reference_steps)

    def set_hover_thrust(self, autopilot_hover_norm: float) -> None:
        """The autopilot's own hover thrust (e.g. ArduCopter's MOT_THST_HOVER): a vehicle
        hovering at h instead of the configured h0 meets, with our thrust model, a vertical
        disturbance of g (h / h0 - 1), learnt from the first tick rather than after entry."""
        h0 = self.airframe.hover_thrust_norm
        if math.isfinite(autopilot_hover_norm) and 0.0 < autopilot_hover_norm < 1.0:
            self._d_down_prior_m_s2 = GRAVITY_M_S2 * (autopilot_hover_norm / h0 - 1.0)

    def observe(
        self,
        state: VehicleState,
        *,
        ours: bool,
        thrust_axis_ned: tuple[float, float, float] | None = None,
    ) -> None:
        """Feed the estimator the disturbance measured over the last prediction step.

        ``ours``: the vehicle flies our commands (offboard confirmed), so its specific
        thrust is ours through the motors' lag. Otherwise the autopilot flies (hold or
        takeoff before offboard, or offboard not yet confirmed: PX4's heartbeat shows a
        mode change up to 1 s late) with a thrust we do not know; it is then the one that
        explains the measured vertical acceleration with the assumed vertical disturbance,
        and the horizontal disturbance follows from the measured tilt. That warms the
        estimator on the wind before control starts, whoever flies.

        Over a window of one prediction step: a = (v_new - v_old) / span is the measured
        acceleration, and a = g e_z - f z_b + d with z_b the mean thrust axis, f the mean
        specific thrust.

        Velocities are taken on their own sample times, once per new position sample: a
        velocity repeated while its stream lags (or stops, as when an estimator drops out)
        would read as a disturbance cancelling the whole commanded acceleration. A sample
        older than a prediction step clears the history: nothing is learnt across a gap.

        ``thrust_axis_ned``: the body z axis in NED at ``state``'s attitude, if the caller
        has it (the tick computes it once).

        Scalar arithmetic on the samples' floats (a window holds a few of them: numpy's
        per-call overhead was most of this step's 120 us), in numpy's order, so that the
        numbers are numpy's to the last bit.
        """
        dt_s = self.config.dt_s
        history = self._history
        if state.position_age_s > dt_s:
            history.clear()
            return
        t_vel = state.time_s - state.position_age_s
        if history and t_vel <= history[-1][0] + 1e-9:
            return  # no new velocity sample since the last observation
        thrust = GRAVITY_M_S2 * self._thrust_flown_norm / self.airframe.hover_thrust_norm
        if thrust_axis_ned is None:
            thrust_axis_ned = attitude_to_axis_xyz(*state.euler_rad)
        vx, vy, vz = state.vel_ned_m_s.tolist()
        history.append((t_vel, vx, vy, vz, *thrust_axis_ned, thrust if ours else math.nan))
        if len(history) < 2:
            return
        newest = history[-1]
        # the oldest sample still within one prediction step; the older ones never will be
        # again (velocity times only grow), so they leave the window for good
        while len(history) > 1 and not newest[0] - history[0][0] <= dt_s + 1e-9:
            history.popleft()
        oldest = history[0]
        span = newest[0] - oldest[0]
        if oldest is newest or span < 0.5 * dt_s:
            return
        window = history  # (oldest .. newest: len >= 2, their times differ)
        m = len(window)
        acc_x = (newest[1] - oldest[1]) / span
        acc_y = (newest[2] - oldest[2]) / span
        acc_z = (newest[3] - oldest[3]) / span
        # the thrust acting between two samples: the mean of the two (trapezoid), not the
        # first alone (a rising thrust's step would read as a disturbance); the sums run in
        # numpy's order for a (m, 3) array's mean over its rows: one row after the other
        sax = say = saz = 0.0
        svx = svy = svz = 0.0
        f_mids: list[float] = []
        f_nan = False
        prev = None
        for o in window:
            if prev is not None:
                if prev is oldest:
                    sax = 0.5 * (o[4] + prev[4])
                    say = 0.5 * (o[5] + prev[5])
                    saz = 0.5 * (o[6] + prev[6])
                else:
                    sax += 0.5 * (o[4] + prev[4])
                    say += 0.5 * (o[5] + prev[5])
                    saz += 0.5 * (o[6] + prev[6])
                f_mids.append(0.5 * (o[7] + prev[7]))
                svx += o[1]
                svy += o[2]
                svz += o[3]
            else:
                svx, svy, svz = o[1], o[2], o[3]
            f_nan = f_nan or math.isnan(o[7])
            prev = o
        n_mid = m - 1
        axis_x, axis_y, axis_z = sax / n_mid, say / n_mid, saz / n_mid
        if f_nan:
            if axis_z < 0.5:  # beyond 60 deg of tilt the vertical balance says nothing
                return
            # the autopilot's thrust: the one that gives the measured vertical acceleration
            # with the assumed vertical disturbance
            f_mean = (GRAVITY_M_S2 + self._d_down_prior_m_s2 - acc_z) / axis_z
        else:
            f_mean = _pairwise_sum(f_mids) / n_mid
        # d_meas = a_meas - (g e_z - f z_b)
        d_meas = np.array([
            acc_x - (0.0 - f_mean * axis_x),
            acc_y - (0.0 - f_mean * axis_y),
            acc_z - (GRAVITY_M_S2 - f_mean * axis_z),
        ])  # fmt: skip
        # d_meas is the mean disturbance over the window: pair it with the mean velocity
        # over the same window (drag at the window's start would be a 1/2-window lag)
        z = np.array([svx / m, svy / m, svz / m])
        residual, lwpr = self._residual, self.estimator
        if residual is not None and isinstance(lwpr, LwprPerturbation):  # (set with LWPR only)
            residual.observe(z, d_meas - lwpr.predict_raw(z))
        self.estimator.observe(z, d_meas)

    def feedforward(self, refs: FloatArray) -> FloatArray:
        """(N, 3) commands that make the model's lagged acceleration follow the reference's.

        Exact inverse of ``a[k+1] = alpha a[k] + (1 - alpha) u[k]`` along the reference
        accelerations ``refs[:, 6:9]`` (a_1..a_N, ``refs`` (N, 9) = stages 1..N); a_0 is
        extrapolated linearly from a_1 and a_2 (exact for a piecewise-linear reference).
        """
        a_ref = refs[:, 6:9]
        a = self._a_stages  # the tick's scratch (N + 1, 3): a_0..a_N
        if a.shape[0] != len(a_ref) + 1:
            a = np.empty((len(a_ref) + 1, 3))
        a[0] = 2.0 * a_ref[0] - a_ref[1] if len(a_ref) >= 2 else a_ref[0]
        a[1:] = a_ref
        return self.lag_inverse(a)

    def disturbance_drift(self, d_var: FloatArray) -> FloatArray:
        """(N, 9): the state x_1..x_N the disturbance's variation ``d_var`` (N + 1, 3) along
        the horizon (its value at x_0..x_N less the estimate now) adds to the model's, from
        x_0 with no input: ``s[k+1] = A s[k] + E d_var[k]``, ``s[0] = 0``; p and v only.

        The QP's model carries the disturbance estimate now as a constant (``c~``), while
        ``u_p`` cancels the disturbance expected at each stage. The model with the varying
        disturbance is the constant one's state plus ``s`` (linear), so its cost on
        ``x - r`` is the constant model's on ``x - (r - s)``: the QP held to ``r - s`` is
        exact, and with it ``u_p`` tracks the reference at no cost. Held to ``r``, the plan
        counted on ``u_p``'s compensation moving the state off the reference and fought it:
        a steady 1.8 cm outside the circle (the drag turning with the velocity), and the
        vertical sag in wind (the inflow loss changing with the climb rate).
        """
        h = self.config.dt_s
        drift = self._drift
        n = drift.shape[0]
        d = d_var[:n]  # d over step k: the one at x_k (k = 0..N-1)
        # v: h * sum_{j<=k} d_j; p: sum_{j<=k} (h v_j + h^2/2 d_j), v_j before step j
        np.cumsum(d, axis=0, out=drift[:, 3:6])
        drift[:, 3:6] *= h
        v_before = drift[:, 3:6] - h * d
        np.cumsum(h * v_before + (0.5 * h * h) * d, axis=0, out=drift[:, 0:3])
        return drift

    def lag_inverse(self, a: FloatArray) -> FloatArray:
        """(N, 3) commands that make the lagged acceleration follow ``a`` (N+1, 3), the
        values at x_0..x_N: ``u_k = (a_{k+1} - alpha a_k) / (1 - alpha)``."""
        out: FloatArray = (a[1:] - self.acc_alpha * a[:-1]) / self._one_minus_alpha
        return out

    def achieved_acceleration(
        self,
        state: VehicleState,
        *,
        ours: bool = True,
        thrust_axis_ned: tuple[float, float, float] | None = None,
    ) -> FloatArray:
        """The acceleration (NED, gravity compensated) the measured attitude produces with the
        thrust flown: the model's ``a`` state now. ``ours``: the vehicle flies our thrust
        (through the motors' lag); else the autopilot's, taken as the one that holds
        altitude against the assumed vertical disturbance. ``thrust_axis_ned``: the body z
        axis in NED at ``state``'s attitude, if the caller has it."""
        if thrust_axis_ned is None:
            thrust_axis_ned = attitude_to_axis_xyz(*state.euler_rad)
        ax, ay, az = thrust_axis_ned
        thrust = self._thrust_flown_norm
        if not ours or math.isnan(thrust):
            thrust = self._balance_thrust_norm(az)
        # attitude_to_accel's g e_z - (g f / f_hover) z_b, element by element
        k = GRAVITY_M_S2 * thrust / self.airframe.hover_thrust_norm
        return np.array([0.0 - k * ax, 0.0 - k * ay, GRAVITY_M_S2 - k * az])

    def _balance_thrust_norm(self, axis_down: float) -> float:
        """The thrust that holds altitude at a tilt whose thrust axis has ``axis_down`` as
        its NED z component, against the assumed vertical disturbance."""
        frame = self.airframe
        f = (GRAVITY_M_S2 + self._d_down_prior_m_s2) / max(axis_down, 0.5)
        return min(max(frame.hover_thrust_norm * f / GRAVITY_M_S2, frame.min_thrust_norm),
                   frame.max_thrust_norm)  # fmt: skip

    def _advance_thrust(self, ours: bool, achieved_thrust_norm: float) -> None:
        """One loop period of the motors' lag towards the last command (ours), or the
        autopilot's thrust taken as flown (not ours)."""
        if not ours or math.isnan(self._thrust_flown_norm) or math.isnan(self._last_thrust_norm):
            self._thrust_flown_norm = achieved_thrust_norm
            return
        self._thrust_flown_norm += self._thrust_gain * (
            self._last_thrust_norm - self._thrust_flown_norm
        )

    def _entry_ramp(
        self, acc: FloatArray, achieved: FloatArray, t_s: float, ours: bool, d_hat: FloatArray
    ) -> FloatArray:
        """The command rate-limited after an entry: from the vehicle's acceleration at the
        first tick after a gap (entry, re-entry after a failsafe), horizontally by at most
        ``entry_jerk_m_s3`` per second, and within ``entry_max_acc_m_s2`` of what holds
        against the estimated disturbance ``d_hat``, until ``entry_ramp_s`` after the autopilot is
        confirmed to fly ours (the caller limits the tilt of what it returns)."""
        cfg = self.config
        if t_s - self._last_tick_s > 3.0 * self.loop_period_s:  # control (re)starts
            self._ramp_acc = limit_tilt(achieved.copy(), self.acc_limits)
            self._ramp_end_s = math.inf
        self._last_tick_s = t_s
        if self._ramp_acc is None:
            return acc
        if ours and math.isinf(self._ramp_end_s):
            self._ramp_end_s = t_s + cfg.entry_ramp_s
        if t_s >= self._ramp_end_s:
            self._ramp_acc = None
            return acc
        # horizontally only: a horizontal change is a tilt, which the attitude loop flies
        # with its lag (the jolt); the vertical is thrust alone, and braking a climb that is
        # still under way at entry (ArduCopter's takeoff hands over climbing) needs it whole
        # Within entry_max_acc_m_s2 of what holds against the estimated disturbance, as a
        # vector: the QP buys horizontal authority under the tilt polygon with thrust, so a
        # command whose horizontal part is held back here must not keep the climb it came
        # with (ArduCopter re-entering in 6 m/s wind climbed 0.5 m on it).
        hold = -d_hat
        extra = acc - hold
        extra_norm = float(np.linalg.norm(extra))
        if extra_norm > cfg.entry_max_acc_m_s2:
            acc = hold + extra * (cfg.entry_max_acc_m_s2 / extra_norm)
        vmax = cfg.entry_max_vertical_acc_m_s2
        acc[2] = min(max(acc[2], hold[2] - vmax), hold[2] + vmax)
        step = acc - self._ramp_acc
        vertical = step[2]
        step[2] = 0.0
        norm = float(np.linalg.norm(step))
        max_step = cfg.entry_jerk_m_s3 * self.loop_period_s
        if norm > max_step:
            step *= max_step / norm
        step[2] = vertical
        ramp = self._ramp_acc + step
        if not ours:
            # Until offboard is confirmed the autopilot may still fly its own (PX4 takes
            # setpoints only once it switches, and shows the switch up to 1 s late): the
            # ramp stays within what a vehicle flying it would lag behind by, so it cannot
            # run ahead unflown and reach the vehicle as a step (+3 m/s^2 after a freeze).
            lead = ramp - achieved
            lead[2] = 0.0
            lead_norm = float(np.linalg.norm(lead))
            if lead_norm > self._ramp_lead_m_s2:
                ramp[:2] = achieved[:2] + lead[:2] * (self._ramp_lead_m_s2 / lead_norm)
        self._ramp_acc = ramp
        return ramp.copy()

    def position_tick(
        self, state: VehicleState, reference: ReferenceHorizon, *, learn: bool = True
    ) -> PositionOutput:
        """One position-loop tick towards ``reference`` (its stages 1..N for x[1..N], its
        heading now for the attitude).

        ``learn``: the vehicle is confirmed to fly our commands (offboard). Before, the
        estimator still learns, with the autopilot's thrust inferred (:meth:`observe`), so
        it is warm when control starts; the command is rate-limited from the first tick of
        an entry until ``entry_ramp_s`` after confirmation (:meth:`_entry_ramp`).

        With the px4 baseline (no controller: the autopilot flies the reference) the tick
        is the level hover, which only the flight log shows.
        """
        controller = self.controller
        if controller is None:
            return self.hover(state)
        t0 = time.perf_counter()
        dead_time = self.dead_time
        axis = attitude_to_axis_xyz(*state.euler_rad)  # once: three steps below read it
        axis_down = axis[2]
        self._advance_thrust(learn, self._balance_thrust_norm(axis_down))
        achieved = self.achieved_acceleration(state, ours=learn, thrust_axis_ned=axis)
        # the QP starts from the state fused with the model (control/state_filter.py): its
        # answer to the estimate's smooth error was most of the Neural-Fly rows' error. The
        # disturbance is learnt and looked up from the measured velocity: learnt from the
        # fused one, LWPR would learn back its own estimate the filter was predicted with
        pos_x0, vel_x0 = self._state_filter.update(
            state.time_s - state.position_age_s, state.pos_ned_m, state.vel_ned_m_s,
            achieved, self._d_hat_last,
        )
        # the velocity the disturbance is learnt and looked up at
        # ([position.state_filter] feed_estimator): the estimate's smooth error is no
        # disturbance
        vel_est = state.vel_ned_m_s
        if self._feed_estimator:
            vel_est = vel_x0
            self.observe(replace(state, vel_ned_m_s=vel_x0), ours=learn, thrust_axis_ned=axis)
        else:
            self.observe(state, ours=learn, thrust_axis_ned=axis)
        age_s = state.position_age_s
        x0 = self._x0
        x0_made = False  # (the compiled LWPR plan wrote x0)
        theta: FloatArray | None = None  # (and stacked θ, the controller's check made)
        d_max = self._d_max
        if not self._nominal_feedforward:
            # the QP's window starts where the command chosen now starts to act
            refs = dead_time.window(reference.stages, self.config.dt_s, self.config.horizon)
            # thesis A.1: PD takes its acceleration feedforward from the reference horizon
            # itself; the nominal input only cancels the disturbance
            p_est = self.estimator.estimate(vel_est)
            if self._residual is not None:
                p_est = p_est + self._residual.estimate(vel_est)
            d_hat = np.minimum(np.maximum(p_est, -d_max), d_max)
            u_p = np.broadcast_to(-d_hat, (self.config.horizon, 3))
        else:
            # the disturbance at each stage's reference velocity, as the estimator knows it
            # (LWPR's d(v); zero change for the KF observer): the nominal input that keeps the
            # lagged acceleration on a_ref - d along the horizon, not only on a_ref - d_hat.
            # One prediction pass gives both the estimate at v (row 0) and its variation.
            # The variation's origin (its row 0, the disturbance at x_0 is the estimate):
            # without a command dead time, the reference's velocity now. From the measured
            # velocity it carried the estimate's velocity error (EKF2-like: 3 cm/s) times
            # LWPR's slope into u_p and, through the drift, into the plan (Neural-Fly, seed
            # 1: 0 m/s 2.72 -> 2.63 cm, 8.5 m/s 3.16 -> 3.08). With one, x_0 is predicted
            # from the measured state over the dead time and the measured velocity stays the
            # origin: the reference's there lost the drag's turn over ArduPilot's 0.2 s
            # (circle max 0.90 -> 2.0-4.4 cm)
            z_stages = self._z_stages
            plan = self._plan if self._plan_for is self.estimator else self._filtered_plan()
            fused = self._lwpr_plan
            stages = reference.stages
            if (fused is not None and stages.dtype is _F64 and stages.ndim == 2
                    and stages.shape[1] == 9 and stages.flags.c_contiguous
                    and _vec3s(vel_est, pos_x0, vel_x0)):  # fmt: skip
                # the types its entry point takes: the reference window, the query points,
                # LWPR's prediction, the filter's step, the plan, x0 carried over the
                # sample's age and the dead time, and the perturbation in one compiled call
                # (issue 21; its stages named in kernels.lwpr_plan); False: a point not
                # finite, the models one by one below
                args: Any = self.estimator.prediction_args()  # type: ignore[union-attr]
                if args[3] is not self._lwpr_plan_for:  # models replaced: their types may differ
                    plan = self._filtered_plan()
                    fused = self._lwpr_plan
                if fused is not None and plan is not None:
                    _, filter_state, consts = plan
                    dead_args = self._dead
                    if dead_args is None or self._dead_for is not dead_time:
                        dead_args = self._dead_args(consts)
                    dead, lead_base, lead_frac = dead_args
                    sent, missing = dead_time.flight(state.time_s)
                    d_hat = np.empty(3)
                    planned = (vel_est, stages, dead_time.dead_time_s > 0.0, lead_base,
                               lead_frac, args[0], args[1], args[2], z_stages, self._raw,
                               pos_x0, vel_x0, achieved, self._d_hat_last, age_s, d_hat,
                               filter_state, dead, self._u_p, self._refs_window,
                               self._x0_perturbation, sent, missing)  # fmt: skip
                    check = (controller.check_args() if self._plan_step_for is controller
                             else None)  # fmt: skip
                    if check is not None:
                        # and θ with the last controller's KKT check in the same call
                        # (kernels.plan_step: -2 the plan not made, else theta_check's)
                        made = self._plan_step(*planned, *check)
                        x0_made = made > -2
                        if x0_made:
                            theta = controller.checked(made, check)
                    else:
                        x0_made = fused(*planned)
            if not x0_made:  # (the compiled LWPR plan fills them itself)
                # the QP's window starts where the command chosen now starts to act
                refs = dead_time.window(stages, self.config.dt_s, self.config.horizon)
                z_stages[0] = vel_est
                z_stages[1] = stages[0, 3:6] if dead_time.dead_time_s <= 0.0 else z_stages[0]
                z_stages[2:] = refs[:, 3:6]  # the reference's v at x_1..x_N
            if x0_made:
                u_p, refs = self._u_p, self._refs
            elif plan is not None and refs.dtype is _F64 and refs.flags.c_contiguous:
                # LWPR's estimate_along (its filter stepped, the variation) and the plan
                # below in one compiled call after the prediction, the same bits (issue 21)
                kernel, filter_state, consts = plan
                raw = self.estimator.predict_raw_many(z_stages)  # type: ignore[union-attr]
                d_hat = np.empty(3)
                kernel(raw, refs, d_hat, filter_state, consts, self._u_p, self._refs)
                u_p, refs = self._u_p, self._refs
            else:
                p_hat, d_var = self.estimator.estimate_along(z_stages)
                if self._residual is not None:
                    p_hat = p_hat + self._residual.estimate(vel_est)
                if disturbance_plan is not None:
                    # what follows below in one compiled call, the same bits (issue 21: each
                    # numpy call on these small arrays is cold cache lines in real time)
                    d_hat = np.empty(3)
                    disturbance_plan(p_hat, d_var, d_max, refs, self.acc_alpha,
                                     self._one_minus_alpha, self.config.dt_s, self._u_p,
                                     self._refs, d_hat)  # fmt: skip
                    u_p, refs = self._u_p, self._refs
                else:  # the numpy twin (no numba, or a cold start: see common.jit)
                    d_var = d_var[1:] - d_var[1]
                    # (minimum(maximum()): np.clip's values, a third of its cost on these sizes)
                    d_hat = np.minimum(np.maximum(p_hat, -d_max), d_max)
                    d_var = np.minimum(np.maximum(d_hat + d_var, -d_max), d_max) - d_hat
                    u_p = self.feedforward(refs) - d_hat - self.lag_inverse(d_var)
                    # the model carries d_hat alone (a constant c~: the library's parameter
                    # vector); what the disturbance does beyond it along the horizon is exact as
                    # a shift of the references the model's state is held to (see
                    # disturbance_drift)
                    refs = refs - self.disturbance_drift(d_var)
        if not x0_made:
            if age_s > 0.0:
                # The sample is age_s old (real time: 1-11 ms at 100 Hz, the loop not in
                # phase with it; lockstep: 0) and the tracker predicts it on at constant
                # velocity: the velocity flown from lagged the vehicle's by age x
                # acceleration (6.6-10.7 ms x a in the windy figure-8: the turns cut, 1.5-1.8
                # x lockstep's error, issue 21). The model's acceleration carries the QP's
                # initial state on to the tick.
                acc_model = achieved + self._d_hat_last
                vel_x0 = vel_x0 + acc_model * age_s
                pos_x0 = pos_x0 + (0.5 * age_s * age_s) * acc_model
            x0[0:3] = pos_x0
            x0[3:6] = vel_x0
            x0[6:9] = achieved
        self._d_hat_last = d_hat
        if x0_made:  # (the compiled plan carried x0 over the dead time, and made E d_hat)
            perturbation = self._perturbation
        else:
            if dead_time.steps:
                x0[:] = dead_time.ahead(x0, d_hat, state.time_s)
            perturbation = self._e_dist @ d_hat
        if theta is not None:  # (stacked and checked by the compiled plan: the step's rest)
            decision: Decision = controller.decide(theta, t0)
        else:
            decision = controller.step(x0, refs, u_p, perturbation=perturbation)
        acc = self._limit_tilt(np.asarray(decision.u, dtype=np.float64))
        clipped_only = self._tilt_clipped_only
        ramped = self._entry_ramp(acc, achieved, state.time_s, learn, d_hat)
        if ramped is not acc or not clipped_only:
            # (not ramped and only clipped: the limit again is the same clip, the same bits;
            # its compiled entry a machinery less for a cold tick, issue 21)
            acc = self._limit_tilt(ramped)
        dead_time.sent(state.time_s, acc)
        out = self._attitude_target(
            acc, float(reference.yaw_rad[0]), d_hat, decision.source, t0, axis_down
        )
        self._last_thrust_norm = out.thrust_norm
        return out

    def _limit_tilt(self, acc: FloatArray) -> FloatArray:
        """:func:`~epc_offboard.control.models.limit_tilt` of ``acc`` (3,) float64, to the
        last bit: in one compiled call when no horizontal scaling is near (its ~8 numpy calls,
        twice a tick, were cold cache lines in real time; issue 21), else the function."""
        if self._tilt_reach is not None and acc.flags.c_contiguous:
            lim = self.acc_limits
            out = np.empty(3)
            # the compiled ratio's rounding differs from BLAS's by ~1e-16 of the reach: far
            # below 1, the clip alone is the answer either way
            if self._tilt_reach(acc, lim.u_min, lim.u_max, lim.P, lim.p, out) < _TILT_EXACT_BELOW:
                self._tilt_clipped_only = True
                return out
        self._tilt_clipped_only = False
        return limit_tilt(acc, self.acc_limits)

    def _attitude_target(
        self,
        acc: FloatArray,
        yaw_rad: float,
        d_hat: FloatArray,
        source: str,
        t0: float,
        axis_down: float = 1.0,
    ) -> PositionOutput:
        """The attitude and thrust of ``acc``; ``axis_down``: the NED z component of the
        measured thrust axis (the cosine of the tilt flown), for which the thrust is sized
        (``thrust_tilt_ratio_max``)."""
        cfg, frame = self.config, self.airframe
        att = accel_to_attitude(acc, yaw_rad, frame.hover_thrust_norm)
        thrust = att.thrust_norm
        if cfg.thrust_tilt_ratio_max > 1.0 and thrust > 0.0:
            # the vertical part of the thrust at the tilt flown: (g - a_d) / cos(tilt flown),
            # against |g e_z - a| at the target's
            target_down = (GRAVITY_M_S2 - float(acc[2])) / (
                thrust * GRAVITY_M_S2 / frame.hover_thrust_norm
            )
            ratio = target_down / max(axis_down, 0.1)
            bound = cfg.thrust_tilt_ratio_max
            thrust *= min(max(ratio, 1.0 / bound), bound)
        thrust = min(max(thrust, frame.min_thrust_norm), frame.max_thrust_norm)
        return PositionOutput(
            q_target=frames.euler_to_quat(att.roll_rad, att.pitch_rad, att.yaw_rad),
            euler_target_rad=(att.roll_rad, att.pitch_rad, att.yaw_rad),
            thrust_norm=thrust,
            acc_cmd_ned_m_s2=acc,
            p_hat_ned_m_s2=d_hat,
            source=source,
            compute_us=(time.perf_counter() - t0) * 1e6,
        )

    def hover(self, state: VehicleState) -> PositionOutput:
        """The safe command when the position loop cannot answer: level, hover thrust."""
        hover = self.airframe.hover_thrust_norm
        yaw = state.yaw_rad
        self._last_thrust_norm = hover
        return PositionOutput(
            q_target=frames.euler_to_quat(0.0, 0.0, yaw),
            euler_target_rad=(0.0, 0.0, yaw),
            thrust_norm=hover,
            acc_cmd_ned_m_s2=np.zeros(3),
            p_hat_ned_m_s2=np.zeros(3),
            source="fallback",
            compute_us=0.0,
        )
