"""Received message rates: what the autopilot actually streams, against what the loops need.

PX4 streams LOCAL_POSITION_NED at 30 Hz and ATTITUDE_QUATERNION at 50 Hz on its onboard link
until MAV_CMD_SET_MESSAGE_INTERVAL raises them; ArduPilot streams nothing but HEARTBEAT until
asked. The service asks when the link comes up, measures what arrives, and asks again while a
stream falls short, a few times: then the rate the autopilot grants is accepted (PX4 gives
ATTITUDE_QUATERNION ~123 Hz however high the request: asking every 2 s for the whole flight
changed nothing). A stream that does not come at all is asked for again less and less often
(ArduPilot sends no position before its EKF has an origin, ~36 s after boot). Pure
bookkeeping: the caller gives the times (the loops' clock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass(frozen=True)
class RatePlan:
    """What to do about the rates now: ``ask`` (send the requests), the streams still short
    and asked again, the ones not streamed at all, and the ones whose granted rate was just
    accepted (type -> Hz)."""

    ask: bool
    short: tuple[str, ...] = ()
    withheld: tuple[str, ...] = ()
    accepted_hz: dict[str, float] = field(default_factory=dict)


@dataclass
class RateMonitor:
    """Counts arrivals of a fixed set of message types; ``sample`` gives Hz since the last one.

    Only the watched types are counted, so nothing from the wire can grow it.
    """

    wanted_hz: dict[str, float]
    shortfall_ratio: float = 0.9  # below this fraction of the wanted rate: ask again
    settle_requests: int = 3  # requests (the first included) before a short rate is accepted
    max_backoff_s: float = 32.0  # longest wait between requests for a stream not sent at all
    _counts: dict[str, int] = field(default_factory=dict)
    _since_s: float | None = None
    rates_hz: dict[str, float] = field(default_factory=dict)  # the last sample
    accepted_hz: dict[str, float] = field(default_factory=dict)  # granted, short, accepted
    requests: int = 0  # times the rates were asked for
    _asked_at_s: float = -math.inf
    _short_windows: dict[str, int] = field(default_factory=dict)  # in a row, streamed

    def __post_init__(self) -> None:
        self._counts = dict.fromkeys(self.wanted_hz, 0)
        self.rates_hz = dict.fromkeys(self.wanted_hz, 0.0)

    def record(self, msg_type: str) -> None:
        if msg_type in self._counts:
            self._counts[msg_type] += 1

    def sample(self, now_s: float, min_window_s: float = 1.0) -> bool:
        """Close a measuring window if ``min_window_s`` has passed; True when one was closed."""
        if self._since_s is None:
            self._since_s = now_s
            return False
        span = now_s - self._since_s
        if span < min_window_s:
            return False
        self.rates_hz = {k: n / span for k, n in self._counts.items()}
        self._counts = dict.fromkeys(self._counts, 0)
        self._since_s = now_s
        return True

    def short(self) -> list[str]:
        """Watched types whose last measured rate is below ``shortfall_ratio`` of wanted."""
        return [
            k
            for k, want in self.wanted_hz.items()
            if self.rates_hz.get(k, 0.0) < self.shortfall_ratio * want
        ]

    def plan(self, now_s: float, retry_period_s: float, *, measured: bool) -> RatePlan:
        """The rates' next step at ``now_s``; ``measured``: a window closed just now. The
        first call asks; then, on each measured window, a short stream is asked for again
        every ``retry_period_s`` until ``settle_requests`` requests, then its rate accepted
        once two windows in a row were short (for good, unless it stops); a stream not
        sent at all is asked for again after ``retry_period_s`` doubled per request, up to
        ``max_backoff_s``."""
        if self.requests == 0:
            return self._ask(now_s, RatePlan(True))
        if not measured:
            return RatePlan(False)
        newly: dict[str, float] = {}
        short: list[str] = []
        withheld: list[str] = []
        for name, want in self.wanted_hz.items():
            rate = self.rates_hz.get(name, 0.0)
            if name in self.accepted_hz:
                if rate > 0.0:
                    continue
                del self.accepted_hz[name]  # it stopped: ask again
            runs = self._short_windows
            runs[name] = runs.get(name, 0) + 1 if 0.0 < rate < self.shortfall_ratio * want else 0
            if rate >= self.shortfall_ratio * want:
                continue
            if rate <= 0.0:
                withheld.append(name)
            elif self.requests < self.settle_requests:
                short.append(name)
            elif runs[name] >= 2:
                # (two windows short in a row: not a stream that has just begun, which is
                # given another window)
                self.accepted_hz[name] = newly[name] = rate
        plan = RatePlan(False, tuple(short), tuple(withheld), newly)
        if not short and not withheld:
            return plan
        wait_s = retry_period_s
        if not short:
            backoff = retry_period_s * 2.0 ** min(self.requests - 1, 30)
            wait_s = min(self.max_backoff_s, backoff)
        if now_s - self._asked_at_s < wait_s:
            return plan
        return self._ask(now_s, RatePlan(True, plan.short, plan.withheld, newly))

    def _ask(self, now_s: float, plan: RatePlan) -> RatePlan:
        self.requests += 1
        self._asked_at_s = now_s
        return plan
