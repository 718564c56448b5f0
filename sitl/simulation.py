"""One simulated vehicle: physics + environment + autopilot on a vehicle clock. No I/O.

The clock advances in ticks of ``lockstep_period_s`` (5 ms by default), each made of
``physics_steps_per_tick`` physics/autopilot steps (1 kHz by default). Vehicle time is
``tick * lockstep_period_s`` exactly, so timestamps never drift. Random streams (gusts,
surface fluctuation, estimate noise) are independent children of one seed, so the run is
reproducible from ``seed`` and the sequence of commands applied at given ticks.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from epc_offboard.common.frames import FloatArray, euler_to_quat, quat_multiply, quat_normalize
from sitl.ardupilot import ArduCopter
from sitl.autopilot import OFFBOARD, Autopilot
from sitl.params import SimConfig
from sitl.physics import POS, QUAT, RATE, VEL, Environment, QuadrotorModel, initial_state


@dataclass(frozen=True)
class StateEstimate:
    """The published (noisy) state: what the autopilot tells the world over MAVLink."""

    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    q_wxyz: FloatArray
    rate_frd_rad_s: FloatArray


class Simulation:
    def __init__(self, config: SimConfig, seed: int = 0) -> None:
        self.config = config
        env_rng, self._noise_rng = np.random.default_rng(seed).spawn(2)
        self.model = QuadrotorModel(config.vehicle)
        self.environment = Environment(config.environment, env_rng)
        self.autopilot: Autopilot = (
            ArduCopter(config.vehicle, config.autopilot, config.ardupilot)
            if config.sitl.autopilot == "ardupilot"
            else Autopilot(config.vehicle, config.autopilot)
        )
        self.state = initial_state()
        self.tick = 0
        self._dt_s = 1.0 / config.sitl.physics_rate_hz
        self._steps = config.sitl.physics_steps_per_tick
        self.autopilot.update_outer(self.state, 0.0, config.sitl.lockstep_period_s)
        self.last_command = self.autopilot.update_inner(self.state, self._dt_s)
        # the states of the last ticks, oldest first: the published one is the oldest
        self._history: deque[FloatArray] = deque(
            [self.state], maxlen=config.sitl.telemetry_delay_ticks + 1
        )
        # the estimator's error, correlated (NoiseParams.correlation_time_s > 0): its state
        # (12,) [pos, vel, attitude, rate] and the tick it was last advanced to
        self._error: FloatArray | None = None
        self._error_tick = -1
        # real time: the vehicle's time between ticks (us past the newest tick's), which the
        # runner's clock gives; lockstep: none, the vehicle's time is its tick's
        self.since_tick_us: Callable[[], int] = lambda: 0
        # real time: a setpoint whose delay ends between two ticks reaches the rate loop at
        # that physics step (PX4's rate loop runs at 1 kHz on its own clock), not at the
        # next tick; lockstep setpoints arrive on ticks and keep the tick's delivery
        self.setpoints_between_ticks = False

    @property
    def time_s(self) -> float:
        return self.tick * self.config.sitl.lockstep_period_s

    @property
    def time_us(self) -> int:
        """Vehicle time in whole microseconds (MAVLink time_usec): exact, no float drift."""
        return self.tick * round(self.config.sitl.lockstep_period_s * 1e6)

    def now_us(self) -> int:
        """The vehicle's time now (us): its tick's in lockstep; in real time run on by the
        wall clock within the tick (TIMESYNC answers it, setpoints are stamped with it)."""
        return self.time_us + self.since_tick_us()

    @property
    def time_ms(self) -> int:
        """Vehicle time in whole milliseconds (MAVLink time_boot_ms)."""
        return self.time_us // 1000

    def advance_tick(self) -> None:
        """Advance physics and the autopilot by one tick.

        The substeps run on a plain list of floats (``QuadrotorModel.step_list``,
        ``Autopilot.rotor_speeds``): the state is an array again only between ticks, where
        the autopilot's outer loops, the telemetry and the ground truth read it."""
        ap, env, model, dt_s = self.autopilot, self.environment, self.model, self._dt_s
        ap.update_outer(self.state, self.time_s, self.config.sitl.lockstep_period_s)
        if ap.mode == OFFBOARD:
            # the wind profile's time origin: the first tick flown under offboard control,
            # when the service's trajectory starts (sitl.params.EnvironmentParams)
            env.start_profile_clock()
        x = self.state.tolist()
        x_before = x
        speeds = self.last_command.rotor_speed_rad_s.tolist()
        between = self.setpoints_between_ticks and ap.setpoints_between_ticks
        t0_s = self.time_s
        for k in range(self._steps):
            if between and k and ap.setpoints_due(t0_s + k * dt_s):
                ap.apply_due_setpoints(np.array(x), t0_s + k * dt_s)
            speeds = ap.rotor_speeds(x[RATE], dt_s)
            env.advance(dt_s)
            ext = env.surface_force_ned_n(x[POS]).tolist()
            x_before = x
            x = model.step_list(x, speeds, env.wind_ned_m_s.tolist(), ext, dt_s)
        # what the last substep commanded, from the state it started at
        self.last_command = ap.command(speeds, np.array(x_before[QUAT]))
        self.state = np.array(x)
        self._history.append(self.state)
        self.tick += 1

    def estimate(self) -> StateEstimate:
        """The true state ``sitl.telemetry_delay_s`` ago plus seeded Gaussian noise
        (config ``sitl.noise``: white, or an estimator's correlated error)."""
        n = self.config.sitl.noise
        x = self._history[0]
        if n.correlation_time_s > 0.0:
            e = self._correlated_error()
            return StateEstimate(
                pos_ned_m=x[POS] + e[0:3],
                vel_ned_m_s=x[VEL] + e[3:6],
                q_wxyz=quat_normalize(quat_multiply(x[QUAT], euler_to_quat(*e[6:9]))),
                rate_frd_rad_s=x[RATE] + e[9:12],
            )
        rng = self._noise_rng
        dq = euler_to_quat(*(n.attitude_std_rad * rng.standard_normal(3)))
        return StateEstimate(
            pos_ned_m=x[POS] + n.position_std_m * rng.standard_normal(3),
            vel_ned_m_s=x[VEL] + n.velocity_std_m_s * rng.standard_normal(3),
            q_wxyz=quat_normalize(quat_multiply(x[QUAT], dq)),
            rate_frd_rad_s=x[RATE] + n.rate_std_rad_s * rng.standard_normal(3),
        )

    def _correlated_error(self) -> FloatArray:
        """The estimator's error (12,) at the current tick: first-order Gauss-Markov per
        channel, exactly discretised over the ticks since it was last advanced (so the same
        tick gives the same error however often it is asked for), stationary from the start."""
        n = self.config.sitl.noise
        std = np.repeat(
            [n.position_std_m, n.velocity_std_m_s, n.attitude_std_rad, n.rate_std_rad_s], 3
        )
        if self._error is None:
            self._error = std * self._noise_rng.standard_normal(12)
        elif self.tick != self._error_tick:
            dt_s = (self.tick - self._error_tick) * self.config.sitl.lockstep_period_s
            a = math.exp(-dt_s / n.correlation_time_s)
            self._error = a * self._error + std * math.sqrt(1.0 - a * a) * (
                self._noise_rng.standard_normal(12)
            )
        self._error_tick = self.tick
        return self._error
