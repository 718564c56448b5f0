"""The vehicle's lead on the reference along its velocity, learnt per flight
(control/dead_time.py TimingLead, ``[position.timing_lead]``): learnt from a lead hidden in
noise, bounded, nothing learnt without motion, and the position tick holding a vehicle that
leads back. Pure numerics: cheap."""

from __future__ import annotations

import numpy as np
import pytest

from epc_offboard.control.dead_time import TimingLead, TimingLeadConfig
from epc_offboard.control.perturbation import EstimatorConfig
from epc_offboard.control.position import PositionControlConfig, PositionLoop
from epc_offboard.control.types import ReferenceHorizon, VehicleState

PERIOD_S = 0.01


def _fly(lead: TimingLead, true_lead_s: float, seconds: float, noise_m: float = 0.0) -> None:
    """Neural-Fly's figure: north velocity 1.25 cos t, down 1.5 cos 2t, east still; the
    error the vehicle shows is its true lead less the learnt one, times the velocity, plus
    a smooth noise (0.25 s correlation)."""
    rng = np.random.default_rng(3)
    phi = np.exp(-PERIOD_S / 0.25)
    noise = np.zeros(3)
    for k in range(round(seconds / PERIOD_S)):
        t = k * PERIOD_S
        v = np.array([1.25 * np.cos(t), 0.0, 1.5 * np.cos(2.0 * t)])
        noise = phi * noise + noise_m * np.sqrt(1.0 - phi * phi) * rng.standard_normal(3)
        lead.learn((true_lead_s - lead.lead_s) * v + noise, v)


def test_a_lead_in_phase_with_the_velocity_is_learnt_within_a_lap():
    lead = TimingLead(TimingLeadConfig(time_constant_s=1.0, max_s=0.02), PERIOD_S)
    _fly(lead, 0.007, 6.3, noise_m=0.005)  # one lap, the plant's 5 mm of position noise
    assert lead.lead_s[0] == pytest.approx(0.007, abs=0.002)
    assert lead.lead_s[2] == pytest.approx(0.007, abs=0.002)
    assert lead.lead_s[1] == 0.0  # no motion east: nothing learnt there


def test_the_lead_is_bounded_and_off_by_default():
    lead = TimingLead(TimingLeadConfig(time_constant_s=1.0, max_s=0.02), PERIOD_S)
    _fly(lead, -0.1, 10.0)
    np.testing.assert_allclose(lead.lead_s[[0, 2]], -0.02)
    off = TimingLead(TimingLeadConfig(), PERIOD_S)
    assert not off.config.enabled
    _fly(off, 0.01, 2.0)
    x0 = np.arange(9.0)
    off.carry(x0)
    np.testing.assert_array_equal(x0, np.arange(9.0))
    with pytest.raises(ValueError, match="time_constant_s"):
        TimingLeadConfig(time_constant_s=-1.0)
    with pytest.raises(ValueError, match="max_s"):
        TimingLeadConfig(max_s=0.6)


def test_a_hover_teaches_no_lead():
    lead = TimingLead(TimingLeadConfig(time_constant_s=1.0), PERIOD_S)
    for _ in range(500):
        lead.learn(np.array([0.02, -0.01, 0.03]), np.zeros(3))
    np.testing.assert_array_equal(lead.lead_s, 0.0)


def _moving_state() -> VehicleState:
    return VehicleState(
        time_s=1.0, pos_ned_m=np.array([0.0, 0.0, -2.5]), vel_ned_m_s=np.array([1.0, 0.0, 0.0]),
        q_ned_frd=np.array([1.0, 0.0, 0.0, 0.0]), rate_frd_rad_s=np.zeros(3),
        position_age_s=0.0, attitude_age_s=0.0,
    )  # fmt: skip


def test_the_tick_holds_a_vehicle_that_leads_back():
    """On a reference moving north at 1 m/s, a loop that learnt the vehicle leads by 20 ms
    commands less north acceleration than one that learnt nothing, from the same state."""
    free = {"controller": "mpc", "entry_jerk_m_s3": 1e6, "entry_max_acc_m_s2": 100.0,
            "max_jerk_m_s3": 0.0, "command_dead_time_s": 0.0}
    est = EstimatorConfig(kind="none")
    plain = PositionLoop(PositionControlConfig(**free), est)  # type: ignore[arg-type]
    learnt = PositionLoop(PositionControlConfig(
        **free, timing_lead=TimingLeadConfig(time_constant_s=1.0)), est)  # type: ignore[arg-type]
    learnt.timing_lead.lead_s[:] = 0.02
    steps = plain.config.reference_steps
    stages = np.zeros((steps + 1, 9))
    stages[:, 0] = np.arange(steps + 1) * plain.config.dt_s  # north at 1 m/s, from here
    stages[:, 2] = -2.5
    stages[:, 3] = 1.0
    ref = ReferenceHorizon.at_heading(stages, 0.0)
    a_plain = plain.position_tick(_moving_state(), ref, learn=False).acc_cmd_ned_m_s2
    a_learnt = learnt.position_tick(_moving_state(), ref, learn=False).acc_cmd_ned_m_s2
    assert a_learnt[0] < a_plain[0] - 0.05
    np.testing.assert_allclose(learnt.timing_lead.lead_s, 0.02)  # not learning: kept


def test_the_neuralfly_scenario_models_its_plants_delay_and_learns_the_rest():
    """The scenario carries x0 over the plant's own telemetry delay (not a value tuned on
    seeds) and learns the lead left per flight (issue 24's calm row)."""
    import tomllib

    from epc_offboard.tools.sim.scenario import SCENARIO_DIR

    scenario = tomllib.loads((SCENARIO_DIR / "neuralfly.toml").read_text())
    vehicle_path = SCENARIO_DIR.parent / "vehicles" / f"{scenario['vehicle']}.toml"
    vehicle = tomllib.loads(vehicle_path.read_text())
    position = scenario["service"]["position"]
    assert position["state_latency_s"] == vehicle["sitl"]["telemetry_delay_s"]
    lead = TimingLeadConfig(**position["timing_lead"])
    assert lead.enabled
    assert lead.time_constant_s <= 6.3 / 2  # most of it within lap 1
