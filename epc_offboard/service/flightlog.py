"""The flight log: one CSV row per position tick (``log.flight_log_path``), what
``epc-offboard log mcap`` turns into an MCAP file.

Split in two halves across processes (:mod:`epc_offboard.service.logwriter`): the position
tick packs its row into a fixed-size struct (:func:`pack_row`, a few microseconds: no
formatting, no file), and the log writer process formats and writes it (:class:`FlightLog`).
"""

from __future__ import annotations

import csv
import struct
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:  # the writer process imports this module: it needs none of the controller
    from epc_offboard.control.types import PositionOutput, ReferenceHorizon, VehicleState

FLIGHT_LOG_COLUMNS = [
    "t_s", "vehicle_t_s", "phase",
    "pos_n_m", "pos_e_m", "pos_d_m", "vel_n_m_s", "vel_e_m_s", "vel_d_m_s",
    "ref_pos_n_m", "ref_pos_e_m", "ref_pos_d_m", "ref_vel_n_m_s", "ref_vel_e_m_s", "ref_vel_d_m_s",
    "acc_cmd_n_m_s2", "acc_cmd_e_m_s2", "acc_cmd_d_m_s2",
    "p_hat_n_m_s2", "p_hat_e_m_s2", "p_hat_d_m_s2", "thrust_norm",
    "source", "compute_us",
]  # fmt: skip

# t_s, vehicle_t_s, phase, 19 floats (pos, vel, ref pos, ref vel, acc, p_hat, thrust),
# source, compute_us: one fixed-size row (names are short ASCII words)
ROW = struct.Struct("<dd24s19d24sd")


def pack_row(
    t_s: float,
    phase: str,
    state: VehicleState,
    reference: ReferenceHorizon | None,
    out: PositionOutput,
) -> bytes:
    """The row of the tick at loop time ``t_s`` that flew ``state`` with ``out``;
    ``reference``: what the tick flew (its stage 0 is logged), or None when the tick
    failed before it had one (the vehicle's position is logged)."""
    # (tolist: Python floats, a third of the cost of packing numpy scalars one by one)
    if reference is not None:
        ref = reference.stages[0, 0:6].tolist()  # stage 0: p_ned, v_ned
    else:
        ref = [*state.pos_ned_m.tolist(), 0.0, 0.0, 0.0]
    return ROW.pack(
        t_s, state.time_s, phase.encode(),
        *state.pos_ned_m.tolist(), *state.vel_ned_m_s.tolist(), *ref,
        *out.acc_cmd_ned_m_s2.tolist(), *out.p_hat_ned_m_s2.tolist(), out.thrust_norm,
        out.source.encode(), out.compute_us,
    )  # fmt: skip


class FlightLog:
    """An open flight log; rows as :data:`FLIGHT_LOG_COLUMNS` (times 4 decimals, the rest 5).

    ``append``: continue a file (a restarted log writer) instead of starting it afresh."""

    def __init__(self, path: str | Path, *, append: bool = False) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fresh = not append or not path.exists() or path.stat().st_size == 0
        self._file: TextIO = path.open("w" if fresh else "a", newline="")
        self._writer = csv.writer(self._file)
        if fresh:
            self._writer.writerow(FLIGHT_LOG_COLUMNS)

    def write_packed(self, row: bytes) -> None:
        """Format and write one :func:`pack_row` row."""
        t_s, vehicle_t_s, phase, *rest = ROW.unpack(row)
        values, source, compute_us = rest[:19], rest[19], rest[20]
        self._writer.writerow(
            [f"{t_s:.4f}", f"{vehicle_t_s:.4f}", phase.rstrip(b"\0").decode()]
            + [f"{v:.5f}" for v in values]
            + [source.rstrip(b"\0").decode(), f"{compute_us:.1f}"]
        )

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        self._file.close()
