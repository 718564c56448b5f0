"""What the control law exchanges, as typed frozen values: the state it reads, the reference
it tracks, what the position loop hands the attitude loop, and what the cascade sends.

A leaf of ``control/`` (numpy and :mod:`epc_offboard.common.frames` only): ``vehicle/``
decodes MAVLink into these types, ``service/`` encodes the commands, and the flight-log
writer process reads them without loading the controller. NED / FRD frames, SI units.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np
import numpy.typing as npt

from epc_offboard.common import frames
from epc_offboard.common.frames import FloatArray

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class VehicleState:
    """The newest valid state, predicted to ``time_s``. Arrays are NED/FRD, SI units."""

    time_s: float  # vehicle time this state is for
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    q_ned_frd: FloatArray  # [w, x, y, z], body FRD -> world NED
    rate_frd_rad_s: FloatArray
    position_age_s: float  # vehicle time since the position sample this is predicted from
    attitude_age_s: float

    @cached_property
    def euler_rad(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw) Z-Y-X (computed once: a tick reads it several times; the
        arrays are not written after construction)."""
        return frames.quat_to_euler(self.q_ned_frd)

    @property
    def yaw_rad(self) -> float:
        return self.euler_rad[2]


# one stage of the reference: [p_ned (3), v_ned (3), a_ned (3)], the position model's x
STAGE_WIDTH = 9


@dataclass(frozen=True)
class ReferenceHorizon:
    """Position, velocity, acceleration and yaw at stages 0..N of the position model.

    Stage 0 is the reference now; stages 1..N are what the model's x[1..N] should be, one
    prediction step apart. One (N + 1, 9) array holds the translational part (its rows are
    what the QP's references are made of), and the properties are views of it: building or
    reading a horizon copies nothing.

    ``stages``: (N + 1, 9) rows [p_ned (m), v_ned (m/s), a_ned (m/s^2)];
    ``yaw_rad``: (N + 1,) heading (rad) at each stage.
    """

    stages: FloatArray
    yaw_rad: FloatArray

    def __post_init__(self) -> None:
        n = self.stages.shape[0]
        if self.stages.shape != (n, STAGE_WIDTH) or n < 1 or self.yaw_rad.shape != (n,):
            raise ValueError(
                f"a reference horizon is (N + 1, {STAGE_WIDTH}) stages and (N + 1,) yaws, got "
                f"{self.stages.shape} and {self.yaw_rad.shape}"
            )

    @classmethod
    def at_heading(cls, stages: FloatArray, yaw_rad: float) -> ReferenceHorizon:
        """``stages`` (N + 1, 9) flown at one heading ``yaw_rad`` (rad) throughout."""
        yaws = np.empty(stages.shape[0])
        yaws.fill(yaw_rad)  # (cheaper than np.full: this is built every position tick)
        return cls(stages, yaws)

    @classmethod
    def hold(cls, pos_ned_m: npt.ArrayLike, yaw_rad: float, steps: int) -> ReferenceHorizon:
        """At rest at ``pos_ned_m`` (3,) m, heading ``yaw_rad``, for stages 0..``steps``."""
        stages = np.zeros((steps + 1, STAGE_WIDTH))
        stages[:, 0:3] = pos_ned_m
        return cls.at_heading(stages, yaw_rad)

    @property
    def steps(self) -> int:
        """N: the stages ahead of now."""
        return int(self.stages.shape[0]) - 1

    @property
    def ahead(self) -> FloatArray:
        """(N, 9) stages 1..N: the references of x[1..N] as the QP takes them (a view)."""
        out: FloatArray = self.stages[1:]
        return out

    @property
    def pos_ned_m(self) -> FloatArray:
        """(N + 1, 3) m."""
        out: FloatArray = self.stages[:, 0:3]
        return out

    @property
    def vel_ned_m_s(self) -> FloatArray:
        """(N + 1, 3) m/s."""
        out: FloatArray = self.stages[:, 3:6]
        return out

    @property
    def acc_ned_m_s2(self) -> FloatArray:
        """(N + 1, 3) m/s^2."""
        out: FloatArray = self.stages[:, 6:9]
        return out


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


# Where an attitude command comes from: the attitude EPC's decision (hit, solved,
# intermediate, fallback: see control.decision.Source; "fallback" also the P law when the EPC
# raised), or the attitude itself to the autopilot's own loop: by configuration
# (delegated), on a late tick (late), outside the hover linearisation's envelope (envelope),
# or while the rate model does not predict the measured rates (model).
AttitudeSource = Literal[
    "hit", "solved", "intermediate", "fallback", "delegated", "late", "envelope", "model"
]


@dataclass(frozen=True)
class AttitudeCommand:
    """What the cascade sends each attitude tick: the attitude ``q_target`` ([w, x, y, z],
    body FRD -> NED) with body rates ``rates_frd_rad_s`` (3,) (None: the autopilot's own
    attitude loop tracks ``q_target``), the collective thrust ``thrust_norm`` (0..1), and
    its ``source``."""

    q_target: FloatArray
    rates_frd_rad_s: FloatArray | None
    thrust_norm: float
    source: AttitudeSource


@dataclass(frozen=True)
class PositionTarget:
    """What the px4 baseline sends instead of an attitude: the reference now (stage 0), for
    the autopilot's own position controller (SET_POSITION_TARGET_LOCAL_NED). Position (m),
    velocity (m/s), acceleration (m/s^2), each (3,) NED; heading ``yaw_rad``."""

    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    acc_ned_m_s2: FloatArray
    yaw_rad: float

    @classmethod
    def now(cls, reference: ReferenceHorizon) -> PositionTarget:
        """Stage 0 of ``reference``."""
        return cls(reference.pos_ned_m[0], reference.vel_ned_m_s[0], reference.acc_ned_m_s2[0],
                   float(reference.yaw_rad[0]))
