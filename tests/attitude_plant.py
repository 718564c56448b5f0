"""A rigid body behind an autopilot's rate loop, for the attitude loop's closed-loop tests.

Body rates follow the body-rate command after a dead time, through a first-order lag with a
static gain (``rate_response.py``'s model, integrated at 1 kHz); the attitude integrates
the body rates exactly (quaternion). The attitude loop ticks at 200 Hz and sees the state
as an autopilot sends it: sampled at ``sample_hz`` (PX4 delivers ATTITUDE_QUATERNION at about
123 Hz), ``latency_s`` after it was measured (link and estimator; the state tracker sees the
sample's own stamp, so the service cannot know this latency: it is part of the response's
dead time as the service measures it), optionally with white noise on the rates.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from epc_offboard.common import frames
from epc_offboard.control.attitude import AttitudeLoop
from epc_offboard.control.types import PositionOutput, VehicleState

PHYSICS_DT_S = 0.001
TICK_S = 0.005


@dataclass
class Plant:
    dead_time_s: float
    time_constant_s: float
    gain: float = 1.0
    noise_rad_s: float = 0.0
    seed: int = 0
    sample_hz: float = 1000.0
    latency_s: float = 0.0

    def __post_init__(self) -> None:
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.rate = np.zeros(3)
        n = max(1, round(self.dead_time_s / PHYSICS_DT_S))
        self._queue: deque[np.ndarray] = deque([np.zeros(3)] * n, maxlen=n)
        self.rng = np.random.default_rng(self.seed)
        self.t_s = 0.0
        n_lat = round(self.latency_s / PHYSICS_DT_S) + 1
        self._measured: deque[tuple[float, np.ndarray, np.ndarray]] = deque(
            [(0.0, self.q.copy(), self.rate.copy())] * n_lat, maxlen=n_lat
        )
        self._sample = self._measured[0]
        self._next_sample_s = 0.0

    def step(self, cmd: np.ndarray, duration_s: float = TICK_S) -> None:
        a = math.exp(-PHYSICS_DT_S / self.time_constant_s)
        for _ in range(round(duration_s / PHYSICS_DT_S)):
            acting = self._queue[0] if self.dead_time_s > 0 else cmd
            self._queue.append(np.array(cmd, dtype=np.float64))
            self.rate = a * self.rate + (1 - a) * self.gain * acting
            w = self.rate
            dq = frames.quat_multiply(self.q, np.array([0.0, *(0.5 * w * PHYSICS_DT_S)]))
            self.q = self.q + dq
            self.q /= np.linalg.norm(self.q)
            self.t_s += PHYSICS_DT_S
            noise = self.rng.normal(0.0, self.noise_rad_s, 3) if self.noise_rad_s else 0.0
            self._measured.append((self.t_s, self.q.copy(), self.rate + noise))
            if self.t_s >= self._next_sample_s - 1e-9:
                self._next_sample_s += 1.0 / self.sample_hz
                self._sample = self._measured[0]  # what was measured latency_s ago

    def state(self) -> VehicleState:
        """The newest sample delivered, with its own stamp (as the state tracker keeps it)."""
        t_s, q, rate = self._sample
        return VehicleState(
            time_s=t_s, pos_ned_m=np.zeros(3), vel_ned_m_s=np.zeros(3),
            q_ned_frd=q, rate_frd_rad_s=rate, position_age_s=0.0, attitude_age_s=0.0,
        )  # fmt: skip


def target(roll_deg: float, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> PositionOutput:
    e = (math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
    return PositionOutput(
        q_target=frames.euler_to_quat(*e), euler_target_rad=e, thrust_norm=0.5,
        acc_cmd_ned_m_s2=np.zeros(3), p_hat_ned_m_s2=np.zeros(3), source="test", compute_us=0.0,
    )  # fmt: skip


def fly(loop: AttitudeLoop, plant: Plant, goal: PositionOutput, duration_s: float,
        *, gated: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """Tick the loop for ``duration_s``: (tilt_deg (n,), commands (n, 3), quaternion ticks);
    ``gated``: the loop's rate-model gate may hand the attitude to the autopilot (then the
    plant's rate loop is fed by a P law on the attitude error, as an autopilot would)."""
    tilts, cmds, delegated = [], [], 0
    for _ in range(round(duration_s / TICK_S)):
        s = plant.state()
        now = plant.t_s
        if gated and not loop.rate_model_trusted(now):
            loop.attitude_delegated(s, goal, now)
            err = frames.quat_multiply(frames.quat_conjugate(s.q_ned_frd), goal.q_target)
            cmd = np.clip(2.0 * 6.5 * np.sign(err[0]) * err[1:], -4.0, 4.0)
            delegated += 1
        else:
            cmd = loop.attitude_tick(s, goal, now).rates_frd_rad_s
        assert cmd is not None
        plant.step(cmd)
        tilts.append(frames.tilt_deg(plant.q))
        cmds.append(cmd)
    return np.array(tilts), np.array(cmds), delegated
