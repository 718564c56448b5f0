"""Body rates on the delayed SITL, end to end (issue 20, item 1): real processes, real UDP,
lockstep. The bundled personalities answer a body-rate command as the real autopilots did
(PX4: 45 ms + 100 ms; ArduCopter 4.8-dev: 25-35 ms + 40 ms at gain 1.03, the personality
40-50 ms + 25-30 ms at 1.1).

On ArduCopter's response the service's old ArduPilot rate model (100 ms, 0.3 s, 0.9) made
the attitude EPC swing 28 deg in a plain hover (the real ArduCopter's circle flew off with
it); the measured one (40 ms, 45 ms, 1) holds it within 2 deg. PX4's 45 ms + 100 ms alone
the delay-free loop survived in lockstep (1.7 deg); what tipped it over on the real PX4 is
covered by tests/test_attitude_delay.py (telemetry latency on top).
"""

from __future__ import annotations

import math

import pytest

from tests.rig import Rig, early_origin_vehicle

pytestmark = pytest.mark.timeout(240)

MAX_TILT_DEG = 20.0


def hover_tilt_deg(rig: Rig) -> float:
    """The largest tilt (ground truth) while the service flew offboard."""
    import csv

    with (rig.tmp / "flight.csv").open() as fh:
        t_off = [float(r["vehicle_t_s"]) for r in csv.DictReader(fh) if r["phase"] == "offboard"]
    assert t_off, f"never flew offboard:\n{rig.log()}"
    truth = rig.groundtruth()
    tilt = [
        math.degrees(math.acos(min(1.0, max(-1.0, 1.0 - 2.0 * (qx * qx + qy * qy)))))
        for t, qx, qy in zip(truth["t_s"], truth["q_x"], truth["q_y"], strict=True)
        if t_off[0] <= t <= t_off[-1]
    ]
    return max(tilt)


def test_body_rates_hold_a_level_hover_on_ardupilots_shaped_response(tmp_path):
    overrides = {
        "link": {"autopilot": "ardupilot"},
        "attitude": {"mode": "epc"},  # body rates, which "auto" would not fly on ArduPilot
        "mission": {"duration_s": 8.0, "land_at_end": True},
        "trajectory": {"shape": "hover"},
    }
    sitl_args = ("--autopilot", "ardupilot", "--param", "GUID_OPTIONS=8",
                 "--config", str(early_origin_vehicle(tmp_path)))  # fmt: skip
    with Rig(tmp_path, service_overrides=overrides, sitl_args=sitl_args) as rig:
        code = rig.wait_exit(timeout_s=200)
        log = rig.log()
    assert code == 0, log
    tilt = hover_tilt_deg(rig)
    assert tilt < MAX_TILT_DEG, f"max tilt {tilt:.1f} deg in a hover on body rates"
    stats = rig.stats()
    model = stats["attitude_rate_model"]
    assert model["model"]["time_constant_s"] == pytest.approx(0.045)  # ArduPilot's, configured
    assert stats["counters"].get("failsafes", 0) == 0

