"""Received message rates: what the autopilot actually streams, against what the loops need.

PX4 streams LOCAL_POSITION_NED at 30 Hz and ATTITUDE_QUATERNION at 50 Hz on its onboard link
until MAV_CMD_SET_MESSAGE_INTERVAL raises them; ArduPilot streams nothing but HEARTBEAT until
asked. The service asks when the link comes up, measures what arrives, and asks again while a
stream falls short. Pure bookkeeping: the caller gives the times (the loops' clock).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RateMonitor:
    """Counts arrivals of a fixed set of message types; ``sample`` gives Hz since the last one.

    Only the watched types are counted, so nothing from the wire can grow it.
    """

    wanted_hz: dict[str, float]
    shortfall_ratio: float = 0.9  # below this fraction of the wanted rate: ask again
    _counts: dict[str, int] = field(default_factory=dict)
    _since_s: float | None = None
    rates_hz: dict[str, float] = field(default_factory=dict)  # the last sample

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
