"""The autopilot's clock on the service's: when was a sample MEASURED, in local time.

A real autopilot never waits for the companion: a service that reads late (a starved CPU,
a stalled process, a slow link) receives old samples, and judging their age by when they
were read flies them as fresh (a real PX4 read 2.4 s late climbed to 19.7 m). Each sample
carries the autopilot's stamp (``time_boot_ms`` / ``time_usec``, seconds since its boot);
this maps it to the local monotonic clock,

    t_local = t_autopilot + theta        theta: the clock offset, local minus autopilot

from two kinds of evidence (pure bookkeeping, the caller gives every time):

* every sample is an upper bound, ``theta <= received - stamp`` (nothing arrives before it
  is measured). The smallest over the flight tracks the fastest delivery; the bound may
  rise only at ``max_drift`` (clock drift), so a delay that appears later, and lasts, is
  seen as age, not learnt away. A single sample cannot lower it: the bound moves on the
  larger of two successive samples, so one forged or corrupt stamp does not age every
  genuine one.
* MAVLink TIMESYNC (PX4 and ArduPilot answer a request, ``tc1 = 0``, with their time in
  ``tc1``): a round trip sent at ``t1`` and answered at ``t4`` bounds theta to
  ``[t1 - tc1, t4 - tc1]``; its midpoint is the estimate. Only round trips shorter than
  ``max_rtt_s`` are trusted: a service that reads late also reads the answer late, and a
  long round trip is rejected, so a late service never learns its lateness as offset.
  A trusted round trip may move theta either way (the autopilot's clock stepped, a
  simulator fell behind real time and re-anchored), and restarts the stream bound from it.

* the autopilot's clock rate against ours (skew): a simulator running slower than real
  time (Gazebo at a real-time factor of 0.9, a starved SITL) moves theta by 1 - its rate
  every second, far beyond a crystal's drift. Between two round trips the offset is carried
  on at the skew the recent trusted round trips show (the median of their successive
  slopes, so one step of the autopilot's clock or one forged answer does not set it), for at
  most ``skew_horizon_s`` after the newest one, and no longer than ``max_rtt_s`` after a
  request that has had no trusted answer (a late reader's answer is late: its lateness is
  not carried away by the skew): without fresh evidence, samples age again. Before, the
  offset stood still between round trips, and at a rate of 0.9 every sample looked up to
  50 ms old before the next one: the attitude loop judged them late and flew no body rates.

The estimate is the smaller of the two (the stream bound is a bound: an estimate above it
would call a sample measured after it arrived); the bound may rise at the skew too, within
the same horizon. A timeline resync (autopilot reboot: its stamps restart) must
:meth:`reset` the mapping; until the next sample there is none.
"""

from __future__ import annotations

import itertools
import math
import statistics
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

# the autopilot's clock rate against ours, as 1 - rate (s/s): at most a simulator at half real
# time. Only a SLOWER clock is carried on: a faster one (a simulator sprinting to catch up)
# lowers the offset, and the stream bound follows that at once (its fastest delivery); a
# negative skew carried on would only make fresh samples look older
MAX_SKEW = 0.5
SKEW_TRIPS = 9  # the trusted round trips whose successive slopes give the skew (8 slopes)
SKEW_MIN_SPAN_S = 1.0  # ... spanning at least this long (their offsets' noise, over a span)
# a slope only between round trips this far apart: each offset is within half its round trip
# (at most max_rtt_s / 2) of the truth, so a slope's error is at most max_rtt_s / 2 over this
# (0.1 s/s at the default 50 ms), however the answers' delays are chosen
SKEW_MIN_GAP_S = 0.25


@dataclass(frozen=True)
class RoundTrip:
    """One accepted TIMESYNC round trip, local times in s, ``tc1_s`` the autopilot's."""

    sent_s: float
    received_s: float
    tc1_s: float

    @property
    def rtt_s(self) -> float:
        return self.received_s - self.sent_s

    @property
    def offset_s(self) -> float:
        return self.mid_s - self.tc1_s

    @property
    def mid_s(self) -> float:
        """Local time the autopilot's ``tc1_s`` is taken to have been read at."""
        return 0.5 * (self.sent_s + self.received_s)


def skew_of(trips: Sequence[RoundTrip]) -> float:
    """The offset's rate (s/s, 1 - the autopilot's clock rate against ours) the round trips
    ``trips`` (in order) show: the median of their successive slopes (of trips at least
    ``SKEW_MIN_GAP_S`` apart), clipped to [0, ``MAX_SKEW``]; 0 with fewer than three trips
    or a span under ``SKEW_MIN_SPAN_S``. A step of the autopilot's clock (a simulator
    re-anchoring) or one forged answer is one or two slopes of eight, and moves the median
    little."""
    if len(trips) < 3 or trips[-1].mid_s - trips[0].mid_s < SKEW_MIN_SPAN_S:
        return 0.0
    pairs = [(a, b) for a, b in itertools.pairwise(trips) if b.mid_s - a.mid_s >= SKEW_MIN_GAP_S]
    slopes = [(b.offset_s - a.offset_s) / (b.mid_s - a.mid_s) for a, b in pairs]
    if not slopes:
        return 0.0
    return min(MAX_SKEW, max(0.0, statistics.median(slopes)))


class AutopilotClock:
    """Maps the autopilot's stamps to local monotonic time (see the module docstring).

    ``max_drift``: how fast (s/s) the offset may grow without new evidence (clock drift:
    crystals are within 1e-4; the default allows 1e-3). ``max_rtt_s``: the longest TIMESYNC
    round trip trusted. ``skew_horizon_s``: how long after the newest trusted round trip the
    skew it shows carries the offset on.
    """

    def __init__(
        self, max_drift: float = 1.0e-3, max_rtt_s: float = 0.05, skew_horizon_s: float = 1.0
    ) -> None:
        if not (0.0 <= max_drift < 0.1) or max_rtt_s <= 0.0 or skew_horizon_s < 0.0:
            raise ValueError(f"max_drift {max_drift} must be in [0, 0.1), max_rtt_s > 0, "
                             f"skew_horizon_s >= 0 ({max_rtt_s}, {skew_horizon_s})")  # fmt: skip
        self.max_drift = max_drift
        self.max_rtt_s = max_rtt_s
        self.skew_horizon_s = skew_horizon_s
        self.counters = {"timesync_accepted": 0, "timesync_rejected_rtt": 0, "clock_resets": 0}
        self.reset(count=False)

    def reset(self, *, count: bool = True) -> None:
        """Forget everything (the autopilot's timeline restarted)."""
        self._bound_s = math.inf  # the stream's upper bound on theta, at _bound_at_s
        self._bound_at_s = 0.0
        self._last_delay_s = math.inf  # received - stamp of the previous sample
        self._sync: RoundTrip | None = None
        self._trips: deque[RoundTrip] = deque(maxlen=SKEW_TRIPS)
        self._unanswered_s = math.inf  # the first request sent since the newest trusted trip
        self.skew = 0.0  # the offset's rate (s/s) the recent round trips show
        if count:
            self.counters["clock_resets"] += 1

    @property
    def synced(self) -> bool:
        return self._sync is not None

    @property
    def last_round_trip(self) -> RoundTrip | None:
        return self._sync

    def observe(self, stamp_s: float, received_s: float) -> None:
        """A sample stamped ``stamp_s`` (autopilot) was received at ``received_s`` (local)."""
        delay_s = received_s - stamp_s
        # the larger of two successive samples: one outlier alone does not lower the bound
        robust_s = max(delay_s, self._last_delay_s)
        self._last_delay_s = delay_s
        bound_s = self._bound_now(received_s)
        if math.isfinite(robust_s):
            bound_s = min(bound_s, robust_s)
        elif math.isinf(bound_s):
            bound_s = delay_s  # the first sample: the only evidence there is
        self._bound_s, self._bound_at_s = bound_s, received_s

    def requested(self, sent_s: float) -> None:
        """A TIMESYNC request went out at ``sent_s``: unanswered (trusted) by ``sent_s +
        max_rtt_s``, the skew stops carrying the offset on from then."""
        self._unanswered_s = min(self._unanswered_s, sent_s)

    def timesync(self, sent_s: float, tc1_s: float, received_s: float) -> bool:
        """A TIMESYNC answer: our request went out at ``sent_s``, the autopilot's time was
        ``tc1_s``, the answer came at ``received_s``. True when trusted (and used)."""
        trip = RoundTrip(sent_s, received_s, tc1_s)
        if not (0.0 <= trip.rtt_s <= self.max_rtt_s) or not math.isfinite(tc1_s):
            self.counters["timesync_rejected_rtt"] += 1
            return False
        self.counters["timesync_accepted"] += 1
        self._sync = trip
        self._unanswered_s = math.inf
        self._trips.append(trip)
        self.skew = skew_of(self._trips)
        # the stream bound restarts from the round trip's own upper bound: samples lower it
        # again to the fastest delivery, and a stepped clock is not held at its old offset
        self._bound_s, self._bound_at_s = received_s - tc1_s, received_s
        self._last_delay_s = math.inf
        return True

    def _skewed_s(self, from_s: float, to_s: float) -> float:
        """What the skew moves the offset by from local time ``from_s`` to ``to_s``, within
        the horizon after the newest trusted round trip and before a request has gone
        unanswered (none after)."""
        sync = self._sync
        if sync is None or self.skew == 0.0:
            return 0.0
        end_s = min(sync.received_s + self.skew_horizon_s, self._unanswered_s + self.max_rtt_s)
        return self.skew * (min(to_s, end_s) - min(from_s, end_s))

    def _bound_now(self, now_s: float) -> float:
        since_s = max(0.0, now_s - self._bound_at_s)
        rise_s = self._skewed_s(self._bound_at_s, self._bound_at_s + since_s)  # skew >= 0
        return self._bound_s + self.max_drift * since_s + rise_s

    def offset_s(self, now_s: float) -> float | None:
        """theta at local time ``now_s``; None before any evidence."""
        bound_s = self._bound_now(now_s)
        sync = self._sync
        if sync is None:
            return None if math.isinf(bound_s) else bound_s
        # the round trip's estimate (refreshed every request), carried on at the skew (not
        # drifted: its error has no known sign), never above the stream bound
        return min(sync.offset_s + self._skewed_s(sync.mid_s, now_s), bound_s)

    def to_local(self, stamp_s: float, now_s: float) -> float | None:
        """When (local time) a sample stamped ``stamp_s`` was measured; None if unknown."""
        theta = self.offset_s(now_s)
        return None if theta is None else stamp_s + theta

    def to_autopilot(self, local_s: float) -> float | None:
        """The autopilot's time at local time ``local_s``; None if unknown."""
        theta = self.offset_s(local_s)
        return None if theta is None else local_s - theta
