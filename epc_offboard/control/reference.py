"""What the position loop tracks: one typed reference along its prediction horizon.

Every source (a trajectory, the hold point, a planner's live reference) produces a
:class:`ReferenceHorizon`, so :meth:`PositionLoop.position_tick(state, reference)
<epc_offboard.control.position.PositionLoop.position_tick>` is the whole interface, and the
flight log reads the reference now from the same value the tick flew.

Pure numerics (no I/O). NED frame, SI units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from epc_offboard.common.frames import FloatArray

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
