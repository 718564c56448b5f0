"""Acceptance targets of a scenario and their verdicts (pure: reports in, verdicts out).

A scenario TOML declares which methods ``epc-offboard sim --compare`` flies side by side and
what each must achieve, measured on ground truth after the settle time (docs/CONTRACTS.md report)::

    [compare]
    methods = ["epc:lwpr", "epc:none", "pd:none"]     # controller:adaptation

    [[targets]]
    description = "EPC within 2 cm of the circle"
    method = "epc:lwpr"
    metric = "max_error_m"
    max = 0.02                                        # absolute: value <= max

    [[targets]]
    method = "epc:lwpr"
    metric = "rmse_m"
    vs = "pd:none"                                    # relative: value <= ratio * value(vs)
    ratio = 1.0

A target whose methods were not flown in a run is "n/a", never a pass. A target that names a
wind (``wind_speed_m_s``, and ``wind_profile``: steady unless given) judges only runs flown in
that wind; in any other it is left out::

    [[targets]]
    method = "epc:lwpr"
    metric = "mean_error_m"
    max = 0.028
    wind_speed_m_s = 8.5
    wind_profile = "sine:2.4,1"                       # sim --wind-profile's syntax
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from typing import Any, Literal

from epc_offboard.common.cliargs import parse_wind_profile

Metric = Literal["rmse_m", "max_error_m", "mean_error_m", "max_speed_m_s", "constraint_violations"]
TRACKING_METRICS = ("rmse_m", "max_error_m", "mean_error_m")  # under a vehicle's "tracking"
Verdict = Literal["PASS", "FAIL", "n/a"]

CONTROLLERS = ("epc", "pd", "mpc", "px4")
ADAPTATIONS = ("lwpr", "kf", "none")


def parse_method(text: str) -> tuple[str, str]:
    """``"epc:lwpr"`` -> ("epc", "lwpr"); raises ValueError naming the bad part."""
    parts = text.strip().split(":")
    if len(parts) != 2:
        raise ValueError(f"method must be CONTROLLER:ADAPTATION, got {text!r}")
    controller, adaptation = parts
    if controller not in CONTROLLERS:
        raise ValueError(f"method {text!r}: controller must be one of {CONTROLLERS}")
    if adaptation not in ADAPTATIONS:
        raise ValueError(f"method {text!r}: adaptation must be one of {ADAPTATIONS}")
    return controller, adaptation


def method_name(controller: str, adaptation: str) -> str:
    return f"{controller}:{adaptation}"


@dataclass(frozen=True)
class TargetConfig:
    method: str
    metric: Metric
    max: float | None = None  # absolute bound, in the metric's unit
    vs: str | None = None  # or relative to another method's value
    ratio: float = 1.0
    description: str = ""
    wind_speed_m_s: float | None = None  # judged only in this wind (None: in any)
    wind_profile: str = "steady"  # with wind_speed_m_s: and only with this profile

    def __post_init__(self) -> None:
        parse_method(self.method)
        try:
            parse_wind_profile(self.wind_profile)
        except argparse.ArgumentTypeError as exc:
            raise ValueError(f"wind_profile: {exc}") from exc
        if (self.max is None) == (self.vs is None):
            raise ValueError("a target needs exactly one of `max` (absolute) or `vs` (relative)")
        if self.vs is not None:
            parse_method(self.vs)
        if not (math.isfinite(self.ratio) and self.ratio > 0.0):
            raise ValueError(f"ratio must be > 0, got {self.ratio}")
        if self.max is not None and not self.max >= 0.0:
            raise ValueError(f"max must be >= 0, got {self.max}")

    def applies(self, report: dict[str, Any]) -> bool:
        """Whether a run (a sim report: its "wind") is one this target judges."""
        if self.wind_speed_m_s is None:
            return True
        wind = report.get("wind", {})
        profile = parse_wind_profile(self.wind_profile).text
        return math.isclose(float(wind.get("speed_m_s", 0.0)), self.wind_speed_m_s,
                            abs_tol=1e-9) and wind.get("profile", "steady") == profile  # fmt: skip

    @property
    def methods(self) -> tuple[str, ...]:
        return (self.method,) if self.vs is None else (self.method, self.vs)

    def label(self) -> str:
        if self.description:
            return self.description
        if self.vs is None:
            return f"{self.method} {self.metric} <= {self.max:g}"
        factor = "" if self.ratio == 1.0 else f"{self.ratio:g} x "
        return f"{self.method} {self.metric} <= {factor}{self.vs}"


@dataclass(frozen=True)
class CompareConfig:
    methods: tuple[str, ...] = field(default_factory=lambda: ("epc:lwpr",))

    def __post_init__(self) -> None:
        if not self.methods:
            raise ValueError("compare.methods must name at least one method")
        for m in self.methods:
            parse_method(m)
        if len(set(self.methods)) != len(self.methods):
            raise ValueError(f"compare.methods repeats a method: {self.methods}")


def metric_value(report: dict[str, Any], metric: Metric) -> float:
    """The metric over a sim report's vehicles: the worst vehicle (largest value). A figure
    the report has as null (a written report has no NaN: a flight stopped before its metric
    began) is NaN: no figure, which fails a bound."""
    values = []
    for v in report["vehicles"]:
        value = v["tracking"].get(metric) if metric in TRACKING_METRICS else v[metric]
        values.append(math.nan if value is None else float(value))
    return max(values)


def evaluate(
    targets: tuple[TargetConfig, ...], reports: dict[str, dict[str, Any]]
) -> list[dict[str, Any]]:
    """Verdict per target; ``reports`` maps ``controller:adaptation`` to a sim report (of
    one run: one wind). Targets for another wind are left out."""
    out: list[dict[str, Any]] = []
    for t in targets:
        if reports and not t.applies(next(iter(reports.values()))):
            continue
        row: dict[str, Any] = {
            "target": t.label(),
            "method": t.method,
            "metric": t.metric,
            "value": None,
            "bound": None,
            "vs": t.vs,
            "verdict": "n/a",
        }
        if all(m in reports for m in t.methods):
            value = metric_value(reports[t.method], t.metric)
            bound = (
                float(t.max)
                if t.max is not None
                else t.ratio * metric_value(reports[str(t.vs)], t.metric)
            )
            ok = math.isfinite(value) and value <= bound
            row.update(value=value, bound=bound, verdict="PASS" if ok else "FAIL")
        out.append(row)
    return out
