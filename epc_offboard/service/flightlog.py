"""The flight log: one CSV row per position tick (``log.flight_log_path``), what
``epc-offboard log mcap`` turns into an MCAP file."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import TextIO

import numpy as np

from epc_offboard.control.position import PositionOutput
from epc_offboard.control.reference import ReferenceHorizon
from epc_offboard.vehicle.state import VehicleState

FLIGHT_LOG_COLUMNS = [
    "t_s", "vehicle_t_s", "phase",
    "pos_n_m", "pos_e_m", "pos_d_m", "vel_n_m_s", "vel_e_m_s", "vel_d_m_s",
    "ref_pos_n_m", "ref_pos_e_m", "ref_pos_d_m", "ref_vel_n_m_s", "ref_vel_e_m_s", "ref_vel_d_m_s",
    "acc_cmd_n_m_s2", "acc_cmd_e_m_s2", "acc_cmd_d_m_s2",
    "p_hat_n_m_s2", "p_hat_e_m_s2", "p_hat_d_m_s2", "thrust_norm",
    "source", "compute_us",
]  # fmt: skip


class FlightLog:
    """An open flight log; rows as :data:`FLIGHT_LOG_COLUMNS` (times 4 decimals, the rest 5)."""

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file: TextIO = path.open("w", newline="")
        self._writer = csv.writer(self._file)
        self._writer.writerow(FLIGHT_LOG_COLUMNS)

    def write(
        self,
        t_s: float,
        phase: str,
        state: VehicleState,
        reference: ReferenceHorizon | None,
        out: PositionOutput,
    ) -> None:
        """The row of the tick at loop time ``t_s`` that flew ``state`` with ``out``;
        ``reference``: what the tick flew (its stage 0 is logged), or None when the tick
        failed before it had one (the vehicle's position is logged)."""
        if reference is not None:
            ref_pos_ned_m, ref_vel_ned_m_s = reference.pos_ned_m[0], reference.vel_ned_m_s[0]
        else:
            ref_pos_ned_m, ref_vel_ned_m_s = state.pos_ned_m, np.zeros(3)
        self._writer.writerow(
            [f"{t_s:.4f}", f"{state.time_s:.4f}", phase]
            + [f"{v:.5f}" for v in (*state.pos_ned_m, *state.vel_ned_m_s)]
            + [f"{v:.5f}" for v in (*ref_pos_ned_m, *ref_vel_ned_m_s)]
            + [f"{v:.5f}" for v in (*out.acc_cmd_ned_m_s2, *out.p_hat_ned_m_s2, out.thrust_norm)]
            + [out.source, f"{out.compute_us:.1f}"]
        )

    def close(self) -> None:
        self._file.close()
