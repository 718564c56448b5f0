"""The attitude loop (200 Hz): body rates towards the position loop's attitude.

Pure numerics (no asyncio, no MAVLink). :meth:`AttitudeLoop.attitude_tick`: EPC on
x = [roll, pitch, yaw, p, q, r] with body-rate commands as input and a first-order rate
response (the autopilot's rate loop), reference = the position loop's attitude with zero
rates -> body rates + thrust. Outside the envelope where that hover linearisation holds
(:meth:`AttitudeLoop.rates_trusted`) the attitude goes to the autopilot's own loop; when
the EPC cannot answer, :meth:`AttitudeLoop.attitude_fallback` is a P law on the angle error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from epc_offboard.common import frames
from epc_offboard.common.frames import FloatArray
from epc_offboard.control.epc import budgeted_controller
from epc_offboard.control.models import attitude_model
from epc_offboard.control.position import PositionOutput
from epc_offboard.control.qp import MpcProblem
from epc_offboard.vehicle.state import VehicleState

Vec3 = tuple[float, float, float]


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


@dataclass(frozen=True)
class AttitudeOutput:
    rates_frd_rad_s: FloatArray | None  # None: let the autopilot track q_target itself
    thrust_norm: float
    source: str


def attitude_problem(cfg: AttitudeControlConfig) -> MpcProblem:
    """The attitude QP: Euler angles and body rates over ``cfg.horizon`` steps of
    ``cfg.dt_s``, body-rate commands bounded by ``cfg.max_rate_rad_s``."""
    rmax = np.array(cfg.max_rate_rad_s, dtype=np.float64)
    return MpcProblem(
        attitude_model(cfg.dt_s, cfg.rate_time_constant_s),
        horizon=cfg.horizon,
        Q=np.concatenate([cfg.q_angle, cfg.q_rate]),
        R=np.array(cfg.r_rate, dtype=np.float64),
        u_min=-rmax,
        u_max=rmax,
    )


class AttitudeLoop:
    """The attitude loop's numerics for one vehicle: its QP and EPC (``learn_on_miss`` as
    :class:`~epc_offboard.control.position.PositionLoop`'s)."""

    def __init__(self, config: AttitudeControlConfig, *, learn_on_miss: bool = True) -> None:
        self.config = config
        self.problem = attitude_problem(config)
        self.controller = budgeted_controller(
            self.problem, config.library_size, config.query_budget_us, learn_on_miss
        )

    def rates_trusted(self, state: VehicleState, target: PositionOutput) -> bool:
        """Whether the attitude is where the body-rate EPC's hover linearisation holds: tilt
        and distance to the attitude target within ``rates_max_tilt_deg`` /
        ``rates_max_error_deg``. Outside, the attitude goes to the autopilot's own loop."""
        cfg = self.config
        tilt = frames.tilt_deg(state.q_ned_frd)
        error = frames.angle_between_deg(state.q_ned_frd, target.q_target)
        return tilt <= cfg.rates_max_tilt_deg and error <= cfg.rates_max_error_deg

    def _refs(self, state: VehicleState, target: PositionOutput) -> tuple[FloatArray, FloatArray]:
        """x0 (6,) and the references (N, 6) of x[1..N]: the target attitude at rest."""
        roll, pitch, yaw = state.euler_rad
        troll, tpitch, tyaw = target.euler_target_rad
        # take the short way round in yaw: the reference is expressed next to the current yaw
        tyaw = yaw + frames.wrap_pi(tyaw - yaw)
        x0 = np.array([roll, pitch, yaw, *state.rate_frd_rad_s])
        row = np.array([troll, tpitch, tyaw, 0.0, 0.0, 0.0])
        return x0, np.tile(row, (self.config.horizon, 1))

    def attitude_tick(self, state: VehicleState, target: PositionOutput) -> AttitudeOutput:
        x0, refs = self._refs(state, target)
        d = self.controller.step(x0, refs)
        return AttitudeOutput(np.asarray(d.u, dtype=np.float64), target.thrust_norm, d.source)

    def attitude_fallback(self, state: VehicleState, target: PositionOutput) -> AttitudeOutput:
        x0, refs = self._refs(state, target)
        rmax = np.array(self.config.max_rate_rad_s)
        rates = np.clip(self.config.fallback_gain_1_s * (refs[0, :3] - x0[:3]), -rmax, rmax)
        return AttitudeOutput(rates, target.thrust_norm, "fallback")
