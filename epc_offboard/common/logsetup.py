"""Logging for the service: human-readable lines, or JSON lines for journald/log shippers."""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class LogConfig:
    format: Literal["human", "json"] = "human"
    level: Literal["debug", "info", "warning", "error"] = "info"
    flight_log_path: str = ""  # per-tick CSV of the position loop ("" = off)
    tlog_path: str = ""  # MAVLink .tlog of the session ("" = off)
    stats_path: str = ""  # JSON of loop timing, library and counters, written at exit


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "ts": round(record.created, 6),
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry)


HUMAN_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def setup_logging(cfg: LogConfig) -> None:
    """Lines to stderr, written by the thread that logs them; the control process's ``run``
    then hands them to a pump (``logpipe.pipe_stderr``), the helper processes write them
    without blocking (``logpipe.direct_stderr``)."""
    handler = logging.StreamHandler(sys.stderr)
    if cfg.format == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter(HUMAN_FORMAT))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(cfg.level.upper())


class LogGate:
    """At most one log line per key in every ``every_s`` of wall-clock time: lines a peer or
    the wire can trigger at any rate stay bounded (the counters beside them count all)."""

    def __init__(self) -> None:
        self._last: dict[str, float] = {}  # keys are the caller's literals: bounded

    def open(self, key: str, every_s: float) -> bool:
        now = time.monotonic()
        if now - self._last.get(key, -float("inf")) <= every_s:
            return False
        self._last[key] = now
        return True
