"""The Neural-Fly-class plant (issue 24): drag sizing, the aerodynamic terms against their
formula, the estimate's noise and delay, the time-varying wind, and seeded determinism."""

from __future__ import annotations

import argparse
import dataclasses
import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import fsolve

from epc_offboard.common.arducopter import GUIDED
from epc_offboard.common.bundled import bundled_dir
from epc_offboard.common.cliargs import WindProfile, parse_wind_profile
from epc_offboard.common.frames import GRAVITY_M_S2, euler_to_quat, quat_to_rotation
from sitl.ardupilot import ArduCopter
from sitl.autopilot import OFFBOARD, AttitudeSetpoint, Result
from sitl.params import EnvironmentParams, SimConfig, load_sim_config
from sitl.physics import POS, QUAT, ROTOR, VEL, Environment, QuadrotorModel, initial_state
from sitl.simulation import Simulation

NEURALFLY_FILE = bundled_dir() / "vehicles" / "neuralfly_1500g.toml"
NEURALFLY = load_sim_config(NEURALFLY_FILE)
DEFAULT = load_sim_config()
ZERO3 = np.zeros(3)


def trim(model: QuadrotorModel, wind_m_s: float) -> tuple[float, float]:
    """(tilt deg, rotor speed rad/s) that hold position, level in roll, against a wind of
    ``wind_m_s`` blowing towards south: the pitch and the (equal) rotor speeds at which
    the derivative's horizontal and vertical accelerations vanish."""
    wind = np.array([-wind_m_s, 0.0, 0.0])

    def residual(z: np.ndarray) -> list[float]:
        x = initial_state((0.0, 0.0, -10.0))
        x[QUAT] = euler_to_quat(0.0, float(z[0]), 0.0)
        x[ROTOR] = z[1]
        d = model.derivative(x, np.full(4, z[1]), wind, ZERO3)
        return [float(d[3]), float(d[5])]

    pitch_rad, speed_rad_s = fsolve(residual, [0.3, 800.0], xtol=1e-12)
    assert np.allclose(residual(np.array([pitch_rad, speed_rad_s])), 0.0, atol=1e-8)
    return abs(math.degrees(pitch_rad)), float(speed_rad_s)


def test_holding_against_12_m_s_takes_25_to_35_degrees_of_tilt() -> None:
    model = QuadrotorModel(NEURALFLY.vehicle)
    tilt_deg, speed_rad_s = trim(model, 12.0)
    assert 25.0 <= tilt_deg <= 35.0
    assert speed_rad_s < NEURALFLY.vehicle.rotor_speed_max_rad_s  # and it can
    # the shape of Neural-Fly's residual: more tilt with more wind, faster than linearly
    tilts = [trim(model, v)[0] for v in (4.2, 8.5, 12.1)]
    assert tilts == sorted(tilts)
    assert tilts[2] / tilts[0] > 12.1 / 4.2
    # the default vehicle (SIH's linear drag) is another airframe: 51 deg at 12 m/s
    assert trim(QuadrotorModel(DEFAULT.vehicle), 12.0)[0] > 45.0


def aero_oracle(p, x: np.ndarray, wind: np.ndarray) -> np.ndarray:
    """rotorpy's body force, written with numpy: thrust, linear, quadratic and rotor drag."""
    rot = quat_to_rotation(x[QUAT])
    v_air = rot.T @ (x[VEL] - wind)
    rotors = float(np.sum(x[ROTOR]))
    f = np.array([0.0, 0.0, -p.k_f_n_s2 * float(np.sum(x[ROTOR] ** 2))])
    f -= np.asarray(p.drag_coeff_body_n_s_m) * v_air
    f -= np.linalg.norm(v_air) * np.asarray(p.drag_quadratic_body_n_s2_m2) * v_air
    f -= rotors * np.asarray(p.rotor_drag_kg_rad) * v_air
    out: np.ndarray = rot @ f / p.mass_kg + np.array([0.0, 0.0, GRAVITY_M_S2])
    return out


vectors = st.lists(st.floats(-15.0, 15.0), min_size=3, max_size=3)


@settings(max_examples=60, deadline=None)
@given(
    vel=vectors, wind=vectors, angles=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
    speeds=st.lists(st.floats(0.0, 1100.0), min_size=4, max_size=4),
)  # fmt: skip
def test_acceleration_is_the_aerodynamic_model(vel, wind, angles, speeds) -> None:
    for config in (NEURALFLY, DEFAULT):  # with the terms, and the linear drag alone
        x = initial_state((0.0, 0.0, -10.0))
        x[VEL], x[QUAT], x[ROTOR] = vel, euler_to_quat(*angles), speeds
        w = np.asarray(wind, dtype=np.float64)
        d = QuadrotorModel(config.vehicle).derivative(x, np.asarray(speeds), w, ZERO3)
        assert np.allclose(d[VEL], aero_oracle(config.vehicle, x, w), rtol=1e-9, atol=1e-9)


def test_terms_off_leave_the_linear_drag_equations_untouched() -> None:
    """All aerodynamic coefficients 0 (every existing vehicle): no aerodynamic branch runs,
    so the default plant flies bit for bit as before."""
    assert not DEFAULT.vehicle.aerodynamic
    assert QuadrotorModel(DEFAULT.vehicle)._aero_params is None
    assert NEURALFLY.vehicle.aerodynamic


def test_inflow_climbing_loses_thrust_descending_gains_it() -> None:
    model = QuadrotorModel(NEURALFLY.vehicle)
    hover = math.sqrt(NEURALFLY.vehicle.mass_kg * GRAVITY_M_S2 / (4 * NEURALFLY.vehicle.k_f_n_s2))
    acc_down = []
    for climb_m_s in (-2.0, 0.0, 2.0):
        x = initial_state((0.0, 0.0, -10.0))
        x[VEL] = (0.0, 0.0, -climb_m_s)
        x[ROTOR] = hover
        acc_down.append(float(model.derivative(x, np.full(4, hover), ZERO3, ZERO3)[5]))
    descending, still, climbing = acc_down
    assert still == pytest.approx(0.0, abs=1e-9)
    assert climbing > 0.0 > descending  # (NED: positive is down, less lift)
    # the rotors' share (k_z sum w v) beyond the body's quadratic drag
    k_z = NEURALFLY.vehicle.rotor_drag_kg_rad[2]
    body = NEURALFLY.vehicle.drag_quadratic_body_n_s2_m2[2] * 4.0
    assert climbing * NEURALFLY.vehicle.mass_kg == pytest.approx(4 * hover * k_z * 2.0 + body)


def sim_with(config: SimConfig, seed: int = 0) -> Simulation:
    return Simulation(config, seed=seed)


def test_correlated_estimate_noise_has_its_spread_and_time_constant() -> None:
    """EKF2-like error: Gauss-Markov of the configured std and correlation time, one draw
    per tick however often the estimate is asked for."""
    cfg = dataclasses.replace(
        NEURALFLY, sitl=dataclasses.replace(NEURALFLY.sitl, telemetry_delay_s=0.0)
    )
    sim = sim_with(cfg, seed=3)
    noise, period_s = cfg.sitl.noise, cfg.sitl.lockstep_period_s
    errors = []
    for _ in range(40_000):  # 200 s of ticks: 800 correlation times
        sim.tick += 1  # the error's clock; the vehicle stays where it is
        first = sim.estimate()
        again = sim.estimate()
        assert np.array_equal(first.pos_ned_m, again.pos_ned_m)
        errors.append(first.pos_ned_m - sim.state[POS])
    e = np.asarray(errors)[:, 0]
    assert np.std(e) == pytest.approx(noise.position_std_m, rel=0.15)
    lag = round(noise.correlation_time_s / period_s)
    rho = float(np.corrcoef(e[:-lag], e[lag:])[0, 1])
    assert rho == pytest.approx(math.exp(-1.0), abs=0.08)


def test_white_noise_default_is_unchanged() -> None:
    """The default's noise is white: successive estimates of one state differ by the
    configured spread, every call a new draw (as before)."""
    sim = sim_with(DEFAULT)
    draws = np.array([sim.estimate().pos_ned_m - sim.state[POS] for _ in range(4000)])
    assert np.std(draws) == pytest.approx(DEFAULT.sitl.noise.position_std_m, rel=0.1)
    assert abs(float(np.corrcoef(draws[:-1, 0], draws[1:, 0])[0, 1])) < 0.1


def test_telemetry_delay_publishes_the_state_of_ticks_ago() -> None:
    quiet = dataclasses.replace(
        NEURALFLY.sitl.noise, position_std_m=0.0, velocity_std_m_s=0.0, attitude_std_rad=0.0,
        rate_std_rad_s=0.0,
    )  # fmt: skip
    cfg = dataclasses.replace(NEURALFLY, sitl=dataclasses.replace(NEURALFLY.sitl, noise=quiet))
    delay = cfg.sitl.telemetry_delay_ticks
    assert delay * cfg.sitl.lockstep_period_s == pytest.approx(0.015)
    sim = sim_with(cfg)
    sim.state[VEL] = (1.0, 0.0, -1.0)  # moving: each tick's position differs
    sim.state[POS] = (0.0, 0.0, -5.0)
    sim._history.clear()
    sim._history.append(sim.state.copy())
    truth = [sim.state.copy()]
    for _ in range(10):
        sim.advance_tick()
        truth.append(sim.state.copy())
        published = sim.estimate().pos_ned_m
        assert np.array_equal(published, truth[max(0, len(truth) - 1 - delay)][POS])


def test_a_delay_not_a_whole_number_of_ticks_is_refused() -> None:
    with pytest.raises(ValueError, match="telemetry_delay_s"):
        dataclasses.replace(NEURALFLY.sitl, telemetry_delay_s=0.012)


def test_sine_wind_is_neural_flys_8_5_plus_2_4_sin_t() -> None:
    params = EnvironmentParams(
        wind_speed_m_s=8.5, wind_dir_deg=-90.0, wind_sine_amplitude_m_s=2.4,
        wind_sine_rate_rad_s=1.0,
    )  # fmt: skip
    env = Environment(params, np.random.default_rng(0))
    env.start_profile_clock()  # (a Simulation starts it at offboard entry)
    dt_s = 0.001
    for k in range(1, 5001):
        env.advance(dt_s)
        if k % 250 == 0:
            wind = env.wind_ned_m_s
            # towards -90 deg (CCW from east): towards south, -north
            assert wind[0] == pytest.approx(-(8.5 + 2.4 * math.sin(k * dt_s)), abs=1e-12)
            assert wind[1] == pytest.approx(0.0, abs=1e-12)


SINE_WIND = EnvironmentParams(
    wind_speed_m_s=8.5, wind_dir_deg=-90.0, wind_sine_amplitude_m_s=2.4, wind_sine_rate_rad_s=1.0,
    wind_sine_phase_rad=0.5,
)  # fmt: skip


def _winds_after_hand_over(personality: str, hand_over_s: float) -> tuple[list[float], float]:
    """North wind after each tick of 2 s under offboard, handed over after ``hand_over_s``
    of armed waiting; and the steady wind before it."""
    cfg = dataclasses.replace(
        NEURALFLY, environment=SINE_WIND,
        sitl=dataclasses.replace(NEURALFLY.sitl, autopilot=personality),
        ardupilot=dataclasses.replace(NEURALFLY.ardupilot, ekf_origin_after_boot_s=0.0),
    )  # fmt: skip
    sim = sim_with(cfg)
    ap = sim.autopilot
    if personality == "ardupilot":
        assert isinstance(ap, ArduCopter)
        assert ap.set_number(GUIDED, 0.0) == Result.ACCEPTED
    assert ap.arm(True, 0.0) == Result.ACCEPTED
    before = []
    while sim.time_s < hand_over_s - 1e-9:
        sim.advance_tick()
        before.append(float(sim.environment.wind_ned_m_s[0]))
    assert len(set(before)) == 1  # steady until the hand-over
    setpoint = AttitudeSetpoint(0b111, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.1)
    ap.on_attitude_setpoint(setpoint, sim.time_s)
    if personality == "px4":
        assert ap.set_mode(OFFBOARD, sim.time_s) == Result.ACCEPTED
    after = []
    for _ in range(round(2.0 / sim.config.sitl.lockstep_period_s)):
        ap.on_attitude_setpoint(setpoint, sim.time_s)
        sim.advance_tick()
        assert ap.mode == OFFBOARD
        after.append(float(sim.environment.wind_ned_m_s[0]))
    return after, before[0]


@pytest.mark.parametrize("personality", ["px4", "ardupilot"])
def test_the_sine_winds_time_starts_at_offboard_entry_not_at_the_sitls_start(
    personality: str,
) -> None:
    """Issue 24: on SITL time the hand-over instant alone decided which stroke of the
    figure-8 met the gust's peak (neuralfly: max tilt 32-41.5 deg, error 1.9-9.5 cm). The
    profile's time now starts when the autopilot enters offboard control: handed over at
    3 s or at 4.37 s, the vehicle meets the same wind from then on."""
    early, steady_early = _winds_after_hand_over(personality, 3.0)
    late, steady_late = _winds_after_hand_over(personality, 4.37)
    # before the hand-over: the mean plus the swing at t = 0, held (towards south: -north)
    assert steady_early == steady_late == pytest.approx(-(8.5 + 2.4 * math.sin(0.5)), abs=1e-12)
    assert early == late
    period_s = NEURALFLY.sitl.lockstep_period_s
    expected = [-(8.5 + 2.4 * math.sin((k + 1) * period_s + 0.5)) for k in range(len(early))]
    assert early == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize(
    ("text", "profile"),
    [
        ("steady", WindProfile()),
        ("sine:2.4,1", WindProfile(sine_amplitude_m_s=2.4, sine_rate_rad_s=1.0)),
        ("gusts:1,2", WindProfile(gust_std_m_s=1.0, gust_time_constant_s=2.0)),
        ("sine:2.4,1,0.5+gusts:1.5,3", WindProfile(2.4, 1.0, 0.5, 1.5, 3.0)),
    ],
)
def test_wind_profile_round_trips(text: str, profile: WindProfile) -> None:
    assert parse_wind_profile(text) == profile
    assert parse_wind_profile(profile.text) == profile


@pytest.mark.parametrize(
    "text", ["", "sine", "sine:2.4", "sine:-1,1", "sine:1,0", "gusts:1,nan", "sine:1,1+sine:1,1",
             "breeze:1,1", "sine:1,1,1,1", "sine:a,1"],
)  # fmt: skip
def test_bad_wind_profiles_are_refused_naming_the_text(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape(repr(text))):
        parse_wind_profile(text)


def run(config: SimConfig, seed: int, ticks: int) -> list[np.ndarray]:
    sim = sim_with(config, seed)
    sim.autopilot.arm(True, 0.0)
    out = []
    for _ in range(ticks):
        sim.advance_tick()
        e = sim.estimate()
        out.append(np.concatenate([sim.state, e.pos_ned_m, e.vel_ned_m_s, e.q_wxyz]))
    return out


def test_two_seeded_runs_are_identical_and_another_seed_differs() -> None:
    windy = dataclasses.replace(
        NEURALFLY,
        environment=dataclasses.replace(
            NEURALFLY.environment, wind_speed_m_s=8.5, wind_sine_amplitude_m_s=2.4,
            gust_std_m_s=1.0,
        ),
    )  # fmt: skip
    for personality in ("px4", "ardupilot"):
        cfg = dataclasses.replace(
            windy, sitl=dataclasses.replace(windy.sitl, autopilot=personality)
        )
        a, b, c = run(cfg, 7, 200), run(cfg, 7, 200), run(cfg, 8, 200)
        assert all(np.array_equal(u, v) for u, v in zip(a, b, strict=True))
        assert not all(np.array_equal(u, v) for u, v in zip(a, c, strict=True))
