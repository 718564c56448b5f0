"""The figures `sim` writes: ``flight.png`` of one flight (one or more vehicles).

Drawn so they read at a glance: the flight's phases shaded and named (takeoff, entering
offboard, settle, the window the reported RMSE is measured over, landing), the reference drawn
as what it is (a point for a hover, a line for a path), every vehicle in its own colour and
line style, axes fitted to the data (what is clipped says so), altitude and tilt against their
limits, the library's misses where they happened, failsafes (red) and other unusual events
(orange) marked where they happened, and a flight sim had to stop marked where it stopped.
The title names the scenario, the method, the autopilot personality and the wind.

Times are seconds since each vehicle entered offboard (negative: before), as in the report.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from epc_offboard.common.frames import FloatArray
from epc_offboard.tools.sim.analysis import MISS_SOURCES, VehicleResult

if TYPE_CHECKING:
    from matplotlib.axes import Axes


# one colour and one line style per vehicle: vehicle 1 drawn wide and light under vehicle 2's
# narrow dashed line, so neither hides the other where they fly the same path
VEHICLE_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")
VEHICLE_STYLES = ("-", "--", "-.", ":")
AXIS_COLOURS = {"N": "tab:blue", "E": "tab:orange", "D": "tab:green"}
PHASE_COLOURS = {
    "takeoff": "#d9d9d9",
    "to offboard": "#fde0c5",
    "settle": "#fff3b0",
    "RMSE window": "#d4f0d4",
    "landing": "#dbe4f5",
}
# the normal sequence of the service's phases; any other phase is an event worth marking.
# Waiting for a heartbeat or a fresh state is how every flight starts (ArduPilot's EKF takes
# a while): normal until the first offboard, an event after it
_NORMAL_PHASES = {
    "idle",
    "preflight",
    "streaming",
    "offboard_requested",
    "offboard",
    "landing",
    "done",
}
_STARTING_PHASES = {"wait_heartbeat", "wait_state"}
FAILSAFE_COLOUR = "red"  # a failsafe, or a flight sim stopped
EVENT_COLOUR = "darkorange"  # anything else out of the normal sequence (a pilot took over)
HOVER_SPAN_M = 0.05  # a reference that moves less than this is a point (a hover)


def flight_title(
    scenario: str, method: str, autopilot: str, wind: tuple[float, float], vehicles: int = 1
) -> str:
    """What every figure's title says: the scenario, the method (controller + adaptation),
    the autopilot personality and the wind."""
    speed_m_s, dir_deg = wind
    wind_text = (f"wind {speed_m_s:g} m/s towards {dir_deg:g}° (CCW from east)" if speed_m_s > 0
                 else "no wind")  # fmt: skip
    fleet = f", {vehicles} vehicles" if vehicles > 1 else ""
    who = {"px4": "PX4", "ardupilot": "ArduPilot"}.get(autopilot, autopilot)
    how = method.replace(":", " + ")
    return f"{scenario}: {how}, bundled SITL as {who}, {wind_text}{fleet}"


def vehicle_colour(index: int) -> str:
    return VEHICLE_COLOURS[index % len(VEHICLE_COLOURS)]


def vehicle_style(index: int) -> str:
    return VEHICLE_STYLES[index % len(VEHICLE_STYLES)]


@dataclass(frozen=True)
class PhaseSpan:
    name: str
    start_s: float
    end_s: float


def phase_spans(
    events: list[dict[str, Any]],
    settle_s: float,
    t_first_s: float,
    t_last_s: float,
    *,
    flew_offboard: bool = True,
) -> list[PhaseSpan]:
    """The flight's phases from the report's ``phase_events`` (t_s since offboard entry).

    ``t_first_s``/``t_last_s`` bound the data; a phase whose event is missing is left out,
    except the offboard part, which is inferred from the data when its events are missing
    (unless the vehicle never ``flew_offboard``: then it ends taking off or entering it).
    """
    first: dict[str, float] = {}
    for e in events:
        first.setdefault(str(e.get("phase")), float(e["t_s"]))
    armed = first.get("preflight", t_first_s)
    streaming = first.get("streaming")
    if not flew_offboard:
        end = first.get("done", t_last_s)
        spans = [PhaseSpan("takeoff", max(armed, t_first_s), streaming or end)]
        if streaming is not None:
            spans.append(PhaseSpan("to offboard", streaming, end))
        return [s for s in spans if s.end_s > s.start_s]
    offboard = first.get("offboard", 0.0)
    landing = first.get("landing")
    done = first.get("done", t_last_s)
    end_offboard = landing if landing is not None else t_last_s
    spans = []
    if streaming is not None:
        spans.append(PhaseSpan("takeoff", max(armed, t_first_s), streaming))
        spans.append(PhaseSpan("to offboard", streaming, offboard))
    elif offboard > t_first_s:
        spans.append(PhaseSpan("takeoff", max(armed, t_first_s), offboard))
    settle_end = min(offboard + settle_s, end_offboard)
    if settle_s > 0.0:
        spans.append(PhaseSpan("settle", offboard, settle_end))
    spans.append(PhaseSpan("RMSE window", settle_end, end_offboard))
    if landing is not None:
        spans.append(PhaseSpan("landing", landing, min(done, t_last_s)))
    return [s for s in spans if s.end_s > s.start_s]


def _shade(ax: Axes, spans: list[PhaseSpan], *, label: bool) -> None:
    """Shade the phases; with ``label`` name them just above the plot area."""
    from matplotlib.transforms import blended_transform_factory

    lo, hi = ax.get_xlim()
    trans = blended_transform_factory(ax.transData, ax.transAxes)
    for s in spans:
        ax.axvspan(s.start_s, s.end_s, color=PHASE_COLOURS[s.name], alpha=0.6, lw=0, zorder=0)
        if label and (s.end_s - s.start_s) > 0.011 * len(s.name) * (hi - lo):
            ax.text(
                (s.start_s + s.end_s) / 2.0,
                1.01,
                s.name,
                transform=trans,
                ha="center",
                va="bottom",
                fontsize=7,
                color="0.3",
            )


def events(r: VehicleResult) -> list[tuple[float, str, str]]:
    """(t_s, label, colour) of what is out of a flight's normal sequence: failsafes in red,
    other phases in orange (a wait for state once offboard has begun among them), and where
    sim stopped the flight in red."""
    out = []
    offboard_seen = False
    for e in r.report.get("phase_events", []):
        phase = str(e.get("phase"))
        offboard_seen |= phase == "offboard"
        if phase in _NORMAL_PHASES or (phase in _STARTING_PHASES and not offboard_seen):
            continue
        colour = FAILSAFE_COLOUR if phase == "failsafe" else EVENT_COLOUR
        out.append((float(e["t_s"]), phase, colour))
    if r.report.get("stopped") and len(r.truth_t_s):
        out.append((float(r.truth_t_s[-1]), "stopped by sim", FAILSAFE_COLOUR))
    return out


def mark_events(axes: list[Axes], results: list[VehicleResult]) -> bool:
    """A line at every unusual event (:func:`events`), named on the first axes; True when
    any."""
    from matplotlib.transforms import blended_transform_factory

    any_event = False
    for r in results:
        for t_s, label, colour in events(r):
            any_event = True
            for ax in axes:
                ax.axvline(t_s, color=colour, lw=1.3, alpha=0.8, zorder=5)
            trans = blended_transform_factory(axes[0].transData, axes[0].transAxes)
            axes[0].text(t_s, 0.97, f" {label} v{r.vehicle_id}", transform=trans, color=colour,
                         fontsize=7, va="top", rotation=90)  # fmt: skip
    return any_event


def _time_range(results: list[VehicleResult]) -> tuple[float, float]:
    lo = min(float(np.min(_truth(r)[0])) for r in results)
    hi = max(float(np.max(_truth(r)[0])) for r in results)
    return lo, hi


def _truth_mask(r: VehicleResult) -> np.ndarray:
    """The ground truth samples from arming to disarming (a staggered vehicle's SITL runs on
    after it landed)."""
    phases = {str(e["phase"]): float(e["t_s"]) for e in reversed(r.report.get("phase_events", []))}
    first = float(r.t_s[0]) if len(r.t_s) else np.inf
    last = float(r.t_s[-1]) if len(r.t_s) else -np.inf
    lo = min(phases.get("preflight", -np.inf), first) - 0.5
    hi = max(phases.get("done", np.inf) + 1.0, last)
    return (r.truth_t_s >= lo) & (r.truth_t_s <= hi)


def _truth(r: VehicleResult) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The flight's ground truth from arming to disarming when analysed, else the log's."""
    if not len(r.truth_t_s):
        return r.t_s, r.pos_ned_m, r.vel_ned_m_s
    keep = _truth_mask(r)
    return r.truth_t_s[keep], r.truth_pos_ned_m[keep], r.truth_vel_ned_m_s[keep]


def _truth_tilt(r: VehicleResult) -> tuple[FloatArray, FloatArray]:
    if not len(r.truth_t_s) or len(r.truth_tilt_deg) != len(r.truth_t_s):
        return np.zeros(0), np.zeros(0)
    keep = _truth_mask(r)
    return r.truth_t_s[keep], r.truth_tilt_deg[keep]


def _offboard_mask(r: VehicleResult) -> np.ndarray:
    if not r.report.get("flew_offboard", True) or not len(r.t_s):
        return np.zeros(len(r.t_s), dtype=bool)
    landing = [float(e["t_s"]) for e in r.report.get("phase_events", []) if e["phase"] == "landing"]
    end = landing[0] if landing else float(r.t_s[-1])
    return (r.t_s >= 0.0) & (r.t_s <= end)


def _note(ax: Axes, text: str, *, y: float = 0.02, va: str = "bottom") -> None:
    """A small boxed note in the panel's lower left (what the axes cannot say)."""
    ax.text(0.01, y, text, transform=ax.transAxes, fontsize=7, va=va, ha="left", color="0.2",
            bbox={"fc": "white", "ec": "0.7", "alpha": 0.85}, zorder=8)  # fmt: skip


def _legend_outside(ax: Axes) -> None:
    ax.legend(
        fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, framealpha=0.9
    )


def _draw_path(ax: Axes, results: list[VehicleResult]) -> None:
    """Top view: the reference (a point when hovering, a line otherwise) and each flown path
    under offboard; in cm about the hover point when the whole picture is that small."""
    masks = [_offboard_mask(r) for r in results]
    if not any(np.any(m) for m in masks):
        _draw_drift(ax, results)
        return
    refs = [r.ref_ned_m[m] for r, m in zip(results, masks, strict=True) if np.any(m)]
    flown = [r.pos_ned_m[m] for r, m in zip(results, masks, strict=True)]
    ref_all = np.vstack(refs)
    hover = bool(np.all(np.ptp(ref_all[:, :2], axis=0) < HOVER_SPAN_M))
    everything = np.vstack([ref_all, *flown])[:, :2]
    small = bool(np.all(np.ptp(everything, axis=0) < 0.5))
    origin = ref_all[0, :2] if small else np.zeros(2)
    scale, unit = (100.0, "cm") if small else (1.0, "m")

    def xy(a: FloatArray) -> tuple[FloatArray, FloatArray]:
        return (a[:, 1] - origin[1]) * scale, (a[:, 0] - origin[0]) * scale

    for i, (r, f) in enumerate(zip(results, flown, strict=True)):
        if not len(f):
            continue
        x, y = xy(f)
        wide = i == 0 and len(results) > 1
        ax.plot(
            x,
            y,
            color=vehicle_colour(i),
            ls=vehicle_style(i),
            lw=3.0 if wide else 1.3,
            alpha=0.55 if wide else 0.95,
            label=f"vehicle {r.vehicle_id} (offboard)",
        )
        ax.plot(
            x[:1],
            y[:1],
            "o",
            color=vehicle_colour(i),
            ms=5,
            label="offboard entry" if i == len(results) - 1 else None,
        )
    if hover:
        x, y = xy(refs[0][:1])
        ax.plot(x, y, "kX", ms=11, mec="white", label="reference: hover point", zorder=6)
    else:
        for i, ref in enumerate(refs):
            x, y = xy(ref)
            ax.plot(
                x,
                y,
                color="black",
                lw=0.8,
                alpha=0.7,
                zorder=4,
                label="reference" if i == 0 else None,
            )
    # limits with margins and equal aspect on the data limits, never on the box: a path
    # 10 m long and 0 m wide stays a full-size panel, not a strip
    pts = np.column_stack(xy(np.vstack([ref_all, *flown])))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    half = max(float(np.max(hi - lo)) / 2.0, 0.5) * 1.15
    mid = (lo + hi) / 2.0
    ax.update_datalim(np.array([mid - half, mid + half]))
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    where = " of the hover point" if small else " of home"
    ax.set(
        xlabel=f"east{where} [{unit}]",
        ylabel=f"north{where} [{unit}]",
        title="path under offboard (top view, ground truth)",
    )
    notes = []
    if hover:
        notes.append("the hover point is where the vehicle was when offboard began")
    else:
        notes.append("the trajectory starts where the vehicle was when offboard began")
    if len(results) > 1:
        notes.append("each vehicle flies in its own local frame (NED from its own home):\n"
                     "overlaid to compare, not their positions relative to each other")  # fmt: skip
    _note(ax, "\n".join(notes))
    _legend_outside(ax)


def _draw_drift(ax: Axes, results: list[VehicleResult]) -> None:
    """Top view of vehicles that never flew under offboard: where they went instead."""
    for i, r in enumerate(results):
        _t, pos, _vel = _truth(r)
        ax.plot(pos[:, 1], pos[:, 0], color=vehicle_colour(i), ls=vehicle_style(i), lw=1.3,
                label=f"vehicle {r.vehicle_id} (never under offboard)")  # fmt: skip
    ax.plot([0.0], [0.0], "kX", ms=11, mec="white", label="home", zorder=6)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="east of home [m]", ylabel="north of home [m]",
           title="path from arming (top view, ground truth): never under offboard")  # fmt: skip
    _legend_outside(ax)


def _draw_error(ax: Axes, results: list[VehicleResult], settle_s: float) -> None:
    """Error on ground truth against the tracked reference; the axis fits the RMSE window."""
    window_max = 0.0
    outside_max = 0.0
    if not any(len(r.t_s) for r in results):
        _note(ax, "the service never streamed: no reference to measure against", y=0.5,
              va="center")  # fmt: skip
    for i, r in enumerate(results):
        if not len(r.t_s):
            continue
        err_cm = r.error_m * 100.0
        ax.plot(
            r.t_s,
            err_cm,
            color=vehicle_colour(i),
            ls=vehicle_style(i),
            lw=1.2,
            label=f"vehicle {r.vehicle_id}",
        )
        window = _offboard_mask(r) & (r.t_s >= settle_s)
        if np.any(window) and np.isfinite(r.report["tracking"]["rmse_m"]):
            window_max = max(window_max, float(np.max(err_cm[window])))
            rmse_cm = float(r.report["tracking"]["rmse_m"]) * 100.0
            t_w = r.t_s[window]
            ax.hlines(
                rmse_cm,
                t_w[0],
                t_w[-1],
                color=vehicle_colour(i),
                lw=1.0,
                ls=":",
                label=f"RMSE v{r.vehicle_id} {rmse_cm:.2f} cm",
            )
        if np.any(~window):
            outside_max = max(outside_max, float(np.max(err_cm[~window])))
    top = 1.5 * window_max if window_max > 0 else max(outside_max, 1.0)
    if outside_max > 1.3 * top:
        ax.set_ylim(0.0, top)
        ax.text(
            0.99,
            0.97,
            f"clipped at {top:.2g} cm: up to {outside_max:.3g} cm outside the RMSE window",
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=7,
            color="0.25",
            bbox={"fc": "white", "ec": "0.7", "alpha": 0.85},
        )
    else:
        ax.set_ylim(0.0, 1.1 * max(top, outside_max))
    ax.set(xlabel="time since offboard entry [s]", ylabel="|position error| [cm]")
    ax.set_title("tracking error (ground truth)", pad=14)
    _legend_outside(ax)


def _draw_velocity(ax: Axes, results: list[VehicleResult], bounds_m_s: FloatArray) -> None:
    vmax = 0.0
    for i, r in enumerate(results):
        t, _pos, vel = _truth(r)
        for k, axis in enumerate("NED"):
            label = f"v_{axis}" + (f" v{r.vehicle_id}" if len(results) > 1 else "")
            ax.plot(
                t, vel[:, k], color=AXIS_COLOURS[axis], ls=vehicle_style(i), lw=1.0, label=label
            )
        vmax = max(vmax, float(np.max(np.abs(vel))))
    off_scale = []
    for k, axes_name in ((0, "N,E"), (2, "D")):
        b = float(bounds_m_s[k])
        if not np.isfinite(b):
            continue
        if b <= 1.3 * vmax:
            colour = "red" if k == 0 else "darkred"
            ax.axhline(b, color=colour, ls=":", lw=1.2, label=f"bound ±{b:g} m/s ({axes_name})")
            ax.axhline(-b, color=colour, ls=":", lw=1.2)
        else:
            off_scale.append(f"±{b:g} m/s ({axes_name})")
    if off_scale:
        ax.plot([], [], " ", label="bounds off scale:\n" + ", ".join(off_scale))
    ax.set(
        xlabel="time since offboard entry [s]",
        ylabel="velocity NED [m/s]",
        title="velocity (ground truth) vs bounds",
    )
    _legend_outside(ax)


def _envelope_bound(results: list[VehicleResult], name: str) -> float:
    bounds = results[0].report.get("envelope", {}).get("bounds", {})
    return float(bounds.get(name, np.nan))


def _draw_altitude(ax: Axes, results: list[VehicleResult], settle_s: float) -> None:
    """Altitude above home (ground truth) against the reference's, the envelope's ceiling,
    and the vertical error over the RMSE window written out."""
    lines = []
    for i, r in enumerate(results):
        t, pos, _vel = _truth(r)
        who = f" v{r.vehicle_id}" if len(results) > 1 else ""
        ax.plot(t, -pos[:, 2], color=vehicle_colour(i), ls=vehicle_style(i), lw=1.2,
                label=f"altitude{who}")  # fmt: skip
        if len(r.t_s):
            ax.plot(r.t_s, -r.ref_ned_m[:, 2], color="black", lw=0.8, ls=(0, (4, 3)),
                    label="reference" if i == 0 else None)  # fmt: skip
        window = _offboard_mask(r) & (r.t_s >= settle_s)
        if np.any(window):
            dz_cm = 100.0 * np.abs(r.pos_ned_m[window, 2] - r.ref_ned_m[window, 2])
            rms_cm = float(np.sqrt(np.mean(dz_cm**2)))
            lines.append(f"v{r.vehicle_id} vertical error in the RMSE window: RMS "
                         f"{rms_cm:.2f} cm, max {np.max(dz_cm):.2f} cm")  # fmt: skip
    ceiling = _envelope_bound(results, "ceiling_m")
    if np.isfinite(ceiling):
        ax.axhline(ceiling, color="red", ls=":", lw=1.2, label=f"envelope ceiling {ceiling:g} m")
    if lines:  # above the flight's altitude, below the ceiling
        _note(ax, "\n".join(lines), y=0.62)
    lo, hi = ax.get_ylim()
    ax.set_ylim(min(0.0, lo), hi + 0.1 * (hi - min(0.0, lo)))
    ax.set(xlabel="time since offboard entry [s]", ylabel="altitude above home [m]",
           title="altitude (ground truth) vs reference")  # fmt: skip
    _legend_outside(ax)


def _draw_tilt(ax: Axes, results: list[VehicleResult]) -> None:
    """Tilt (ground truth) against the service's command limit and the envelope's bound."""
    peak = 0.0
    for i, r in enumerate(results):
        t, tilt = _truth_tilt(r)
        if not len(t):
            continue
        who = f" v{r.vehicle_id}" if len(results) > 1 else ""
        ax.plot(t, tilt, color=vehicle_colour(i), ls=vehicle_style(i), lw=1.0,
                label=f"tilt{who}")  # fmt: skip
        peak = max(peak, float(np.max(tilt)))
    limit = _envelope_bound(results, "command_tilt_deg")
    bound = _envelope_bound(results, "max_tilt_deg")
    # the limits drawn only where they do not squash the curve; else written out
    show = bool(np.isfinite(bound)) and peak >= 0.3 * limit
    if show:
        ax.axhline(limit, color="darkred", ls="-.", lw=1.2,
                   label=f"command limit {limit:g}° (envelope.max_tilt_deg)")  # fmt: skip
        ax.axhline(bound, color="red", ls=":", lw=1.2, label=f"envelope {bound:g}°")
        ax.set_ylim(0.0, max(peak * 1.1, bound * 1.05))
    else:
        ax.set_ylim(0.0, max(peak * 1.2, 10.0))
        if np.isfinite(bound):
            _note(ax, f"limits off scale: command {limit:g}°, envelope {bound:g}°", y=0.97,
                  va="top")  # fmt: skip
    ax.set(xlabel="time since offboard entry [s]", ylabel="tilt [deg]",
           title="tilt (ground truth) vs its limit")  # fmt: skip
    if ax.get_legend_handles_labels()[1]:
        _legend_outside(ax)


def _draw_library(ax: Axes, results: list[VehicleResult]) -> None:
    """Misses per second where they happened (a miss: the library had no controller proven
    optimal for that tick), with the totals written out."""
    lines = []
    n = len(results)
    peak = 0
    for i, r in enumerate(results):
        lib = r.report.get("library", {})
        if not lib.get("hits", 0) + lib.get("misses", 0) or not len(r.t_s):
            lines.append(f"v{r.vehicle_id}: no controller library used (not EPC, or no flight)")
            continue
        miss_t = r.t_s[np.isin(r.sources, MISS_SOURCES)]
        lo, hi = np.floor(float(r.t_s[0])), np.ceil(float(r.t_s[-1]))
        edges = np.arange(lo, hi + 1.0, 1.0)
        counts, _ = np.histogram(miss_t, bins=edges)
        ax.stairs(
            counts,
            edges,
            color=vehicle_colour(i),
            ls=vehicle_style(i),
            lw=1.4,
            fill=n == 1,
            alpha=0.8 if n == 1 else 1.0,
            label=f"vehicle {r.vehicle_id}: misses per second",
        )
        peak = max(peak, int(counts.max()) if len(counts) else 0)
        # a rug: one tick per miss, in a row of its own above the counts
        ax.plot(
            miss_t,
            np.full(len(miss_t), 0.80 - 0.06 * i),
            "|",
            color=vehicle_colour(i),
            ms=8,
            transform=ax.get_xaxis_transform(),
            label=f"vehicle {r.vehicle_id}: each miss",
        )
        lines.append(
            f"v{r.vehicle_id}: {lib.get('hits', 0)} hits, {lib.get('misses', 0)} misses "
            f"({100.0 * lib.get('hit_rate', 0.0):.1f} % hits), "
            f"{lib.get('first_lap_misses', 0)} on the first lap, "
            f"{lib.get('qp_solves', 0)} QP solves, "
            f"{lib.get('received_shared', 0)} controllers received"
        )
    ax.set_ylim(0.0, max(peak, 1) * 1.5 + 0.5)
    from matplotlib.ticker import MaxNLocator

    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.text(
        0.01,
        0.98,
        "\n".join(lines),
        transform=ax.transAxes,
        fontsize=7,
        va="top",
        bbox={"fc": "white", "ec": "0.7", "alpha": 0.85},
    )
    ax.set(
        xlabel="time since offboard entry [s]",
        ylabel="misses per second",
        title="EPC library: misses where they happened (ticks: each miss)",
    )
    if any(ax.get_legend_handles_labels()[1]):
        _legend_outside(ax)


def write_figure(
    results: list[VehicleResult],
    vel_bounds_m_s: FloatArray,
    path: Path,
    title: str,
    *,
    settle_s: float = 0.0,
) -> None:
    """``flight.png``: top view, tracking error, altitude, velocity, tilt and library misses
    of each vehicle, with the phases shaded (those of vehicle 1 when there are several);
    ``title``: the scenario, method, autopilot and wind (:func:`flight_title`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(3, 2, figsize=(15, 13), layout="constrained")
    ax_path, ax_err, ax_alt, ax_vel, ax_tilt, ax_lib = axes.ravel()
    time_axes = [ax_err, ax_alt, ax_vel, ax_tilt, ax_lib]
    _draw_path(ax_path, results)
    _draw_error(ax_err, results, settle_s)
    _draw_altitude(ax_alt, results, settle_s)
    _draw_velocity(ax_vel, results, vel_bounds_m_s)
    _draw_tilt(ax_tilt, results)
    _draw_library(ax_lib, results)
    lo, hi = _time_range(results)
    first = results[0].report
    spans = phase_spans(first.get("phase_events", []), settle_s, lo, hi,
                        flew_offboard=first.get("flew_offboard", True))  # fmt: skip
    if not first.get("flew_offboard", True):
        for ax in time_axes:
            ax.set_xlabel("time since the SITL started [s] (never under offboard)")
    for ax in time_axes:
        ax.set_xlim(lo, hi)
        ax.grid(True, alpha=0.3)
    for ax in time_axes:
        _shade(ax, spans, label=ax is ax_err)
    mark_events(time_axes, results)
    ax_path.grid(True, alpha=0.3)
    # the phase colours once, for the whole figure
    whose = " (vehicle 1's)" if len(results) > 1 else ""
    handles = [Patch(color=PHASE_COLOURS[s.name], label=s.name) for s in spans]
    fig.legend(
        handles=handles,
        loc="outside lower center",
        ncols=len(handles) + 1,
        fontsize=8,
        title=f"phases{whose}",
        title_fontsize=8,
        frameon=False,
    )
    fig.suptitle(title, fontsize=12)
    save_once(fig, path)
    plt.close(fig)


def save_once(fig: Any, path: Path, dpi: int = 100) -> None:
    """``fig`` to ``path``, drawn once: savefig with a layout engine draws the whole figure
    twice (once with rendering off, to lay it out, then for real). Laid out here and saved
    without the engine, it gives the same pixels."""
    engine = fig.get_layout_engine()
    if engine is not None:
        engine.execute(fig)
        fig.set_layout_engine(None)  # (not "none": a placeholder engine, drawn twice still)
    fig.savefig(path, dpi=dpi)
