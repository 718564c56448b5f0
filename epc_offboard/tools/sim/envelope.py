"""The sane envelope of a sim flight, and where a flight left it: pure numerics.

A flight outside it is a failed flight whatever the targets say (issue 22: a hover in 15 m/s
of wind flew 20 m from its reference and `sim` exited 0). The envelope is derived from the
scenario and the service's limits:

* distance from the reference ``max_error_m`` while the service streams (the scenario's
  ``[envelope]``, 2 m by default: every method of every scenario stays within 1 m in the
  README's figures), in 3-D;
* horizontal distance ``max_drift_m`` (10 m) while the autopilot flies alone: before the
  service streams from home (a takeoff climbs over it), after it from the last reference (an
  autopilot's landing descends where it is). Wider: PX4's takeoff drifts 2.5 m in an 8 m/s
  wind and recovers, a vehicle blown away drifts on;
* altitude above home at most the scenario's highest reference + ``max_error_m``, at any
  time (a repeated takeoff climbing away is caught before the service ever streams);
* tilt at most the airframe's ``envelope.max_tilt_deg`` + ``tilt_margin_deg``: the commands
  never ask for more, so more is a vehicle out of control;
* vehicle time from the SITL's start at most ``takeoff_budget_s`` + the scenario's duration
  + ``landing_budget_s``: a flight that cannot end (a vehicle blown away before it is ever
  airborne: the service waits for a state it can trust) ends there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from epc_offboard.common.frames import FloatArray


@dataclass(frozen=True)
class EnvelopeConfig:
    """A scenario's ``[envelope]`` table."""

    max_error_m: float = 2.0  # distance from the reference
    max_drift_m: float = 10.0  # horizontal distance while the autopilot flies alone
    tilt_margin_deg: float = 15.0  # beyond the airframe's envelope.max_tilt_deg
    takeoff_budget_s: float = 60.0  # vehicle time from the SITL's start to offboard
    landing_budget_s: float = 60.0  # vehicle time from the end of offboard to landed

    def __post_init__(self) -> None:
        names = ("max_error_m", "max_drift_m", "tilt_margin_deg", "takeoff_budget_s",
                 "landing_budget_s")  # fmt: skip
        for name in names:
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class Envelope:
    """The bounds one flight is judged against (see the module's docstring)."""

    max_error_m: float
    max_drift_m: float
    max_tilt_deg: float
    ceiling_m: float  # altitude above home
    max_flight_s: float  # vehicle time from the SITL's start
    command_tilt_deg: float = 45.0  # the service's own tilt limit (drawn beside the bound)

    def as_dict(self) -> dict[str, float]:
        return {
            "max_error_m": self.max_error_m,
            "max_drift_m": self.max_drift_m,
            "max_tilt_deg": self.max_tilt_deg,
            "ceiling_m": self.ceiling_m,
            "max_flight_s": self.max_flight_s,
            "command_tilt_deg": self.command_tilt_deg,
        }


def envelope_for(
    cfg: EnvelopeConfig, *, altitude_m: float, climb_m: float, duration_s: float,
    max_tilt_deg: float,
) -> Envelope:  # fmt: skip
    """The envelope of a scenario flown at ``altitude_m`` whose reference climbs ``climb_m``
    above it at most, for ``duration_s`` under offboard, by a service whose commands stay
    within ``max_tilt_deg``."""
    return Envelope(
        max_error_m=cfg.max_error_m,
        max_drift_m=cfg.max_drift_m,
        max_tilt_deg=max_tilt_deg + cfg.tilt_margin_deg,
        ceiling_m=altitude_m + max(climb_m, 0.0) + cfg.max_error_m,
        max_flight_s=cfg.takeoff_budget_s + duration_s + cfg.landing_budget_s,
        command_tilt_deg=max_tilt_deg,
    )


@dataclass(frozen=True)
class Breach:
    """Where a flight first left one bound of its envelope, and how far it went."""

    what: str  # "distance from the reference", "drift ...", "altitude", "tilt", "flight time"
    t_s: float  # first sample beyond the bound (the caller's time axis)
    worst: float  # the largest value beyond it
    bound: float
    unit: str

    def describe(self) -> str:
        return (
            f"{self.what} {self.worst:.4g} {self.unit} beyond its bound {self.bound:.4g} "
            f"{self.unit} (from t = {self.t_s:.2f} s)"
        )

    def as_dict(self) -> dict[str, float | str]:
        return {"what": self.what, "t_s": round(self.t_s, 3), "worst": self.worst,
                "bound": self.bound, "unit": self.unit, "text": self.describe()}  # fmt: skip


def tilt_deg_of(q_wxyz: FloatArray) -> FloatArray:
    """(T,) tilt of body z from world down, degrees, of (T, 4) quaternions [w, x, y, z]."""
    q = np.atleast_2d(q_wxyz)
    norm2 = np.sum(q * q, axis=1)
    cos_tilt = 1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2) / np.where(norm2 > 0.0, norm2, 1.0)
    return np.degrees(np.arccos(np.clip(cos_tilt, -1.0, 1.0)))


def breaches(
    env: Envelope,
    t_s: FloatArray,
    pos_ned_m: FloatArray,
    tilt_deg: FloatArray,
    ref_ned_m: FloatArray,
    horizontal: np.ndarray,
    *,
    flight_s: FloatArray,
) -> list[Breach]:
    """Every bound of ``env`` the samples leave, each with its first time and worst value.

    ``t_s`` (T,) the time to report, ``pos_ned_m``/``ref_ned_m`` (T, 3) NED from home,
    ``tilt_deg`` (T,), ``horizontal`` (T,) bool: judge the distance horizontally only,
    ``flight_s`` (T,) vehicle time since the SITL started.
    """
    diff = np.asarray(pos_ned_m, dtype=np.float64) - np.asarray(ref_ned_m, dtype=np.float64)
    alone = np.asarray(horizontal, dtype=bool)
    diff[alone, 2] = 0.0
    distance = np.linalg.norm(diff, axis=1)
    drift = np.where(alone, distance, np.nan)
    checks = (
        ("distance from the reference", np.where(alone, np.nan, distance), env.max_error_m, "m"),
        ("drift while the autopilot flew alone", drift, env.max_drift_m, "m"),
        ("altitude", -np.asarray(pos_ned_m)[:, 2], env.ceiling_m, "m"),
        ("tilt", np.asarray(tilt_deg), env.max_tilt_deg, "deg"),
        ("flight time", np.asarray(flight_s), env.max_flight_s, "s"),
    )
    out = []
    for what, value, bound, unit in checks:
        beyond = np.isfinite(value) & (value > bound)
        if np.any(beyond):
            first = int(np.argmax(beyond))
            out.append(Breach(what, float(t_s[first]), float(np.max(value[beyond])), bound, unit))
    return out
