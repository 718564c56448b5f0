"""Ground-truth CSV: the true state, wind and commands, one row per tick.

Flushed every ``flush_interval_s`` of wall-clock time so a reader (``epc-offboard sim``) can
follow the file while the simulator runs.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sitl.simulation import Simulation

COLUMNS = [
    "t_s",
    "pos_n_m",
    "pos_e_m",
    "pos_d_m",
    "vel_n_m_s",
    "vel_e_m_s",
    "vel_d_m_s",
    "q_w",
    "q_x",
    "q_y",
    "q_z",
    "rate_x_rad_s",
    "rate_y_rad_s",
    "rate_z_rad_s",
    "wind_n_m_s",
    "wind_e_m_s",
    "wind_d_m_s",
    "thrust_cmd_norm",
    "rate_cmd_x_rad_s",
    "rate_cmd_y_rad_s",
    "rate_cmd_z_rad_s",
    "armed",
    "main_mode",
    "sub_mode",
    "rotor_1_rad_s",
    "rotor_2_rad_s",
    "rotor_3_rad_s",
    "rotor_4_rad_s",
    "landed_state",
]

# One row: time, then the true state and wind (9 significant digits), the commands, the
# autopilot's state and the rotor speeds (6 digits). One %-format per row: the SITL writes
# 200 rows a second per vehicle.
_ROW = ",".join(["%.6f", *["%.9g"] * 20, "%d", "%d", "%d", *["%.6g"] * 4, "%d"]) + "\n"


class GroundTruthWriter:
    def __init__(self, path: str | Path, flush_interval_s: float = 1.0) -> None:
        # Held open for the whole run and closed by close(): rows stream in tick by tick.
        self._fh = Path(path).open("w", encoding="ascii", newline="")  # noqa: SIM115
        self._fh.write(",".join(COLUMNS) + "\n")
        self._fh.flush()
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()

    def write(self, sim: Simulation) -> None:
        ap = sim.autopilot
        cmd = sim.last_command
        state = sim.state.tolist()
        self._fh.write(
            _ROW
            % (
                sim.time_s,
                *state[0:13],
                *sim.environment.wind_ned_m_s.tolist(),
                float(cmd.thrust_norm),
                *np.asarray(cmd.rate_cmd_frd_rad_s, dtype=np.float64).tolist(),
                int(ap.armed),
                ap.mode.main,
                ap.mode.sub,
                *state[13:17],
                int(ap.landed_state),
            )
        )
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval_s:
            self._fh.flush()
            self._last_flush = now

    def close(self) -> None:
        self._fh.close()
