"""``epc-offboard fleet router``: a Zenoh router for a fleet, from the eclipse-zenoh package.

For fleets beyond a few vehicles: each vehicle is a Zenoh client of one or more routers
(``[sharing] mode = "client"``, ``connect`` the routers) instead of a peer of every other
vehicle. Where ``zenohd`` is installed it serves as well; this is the same router (zenoh
1.x's Python package opens a session in ``mode: "router"``, with the full routing, TLS,
user-password and access-control stack of zenohd, without its plugins), so any Zenoh client
can use it, not only ours.

Stats: printed as one JSON line on stdout every ``--stats-every`` seconds and at exit, and
answered as JSON on ``epc/router/<zid>/stats`` (and Zenoh's own admin space,
``@/<zid>/router``, lists the sessions when ``adminspace.enabled``). They hold the sessions
open by kind, transports opened and closed, this process's CPU, and the refusals.

Refusals are counted from Zenoh's own log, because Zenoh has no API that reports them: a
refused TLS handshake is logged at WARN (``zenoh_link_tls``), a refused user-password at
DEBUG (``zenoh_transport::unicast::establishment``: the accept steps). This process turns
those targets on, sends Zenoh's log (which it writes to fd 1) through a pipe read by a thread
that counts the matching lines, and passes the rest to stderr; its own stdout is kept for
the stats. Messages an access rule denies are NOT counted here: Zenoh logs a denial at TRACE
only when it is first decided for a key expression (later ones come from a per-key cache,
unlogged), and it logs the cache's precomputed denials of every message kind when a client
merely declares a key expression (zenoh/src/net/routing/interceptor/access_control.rs,
``compute_keyexpr_cache``, ``cached_result_or_action``), so the log neither bounds nor counts
them. A denied publication is observable where it matters: it never arrives. Nor does the
admin space count them: in the pip build (1.10) ``@/<zid>/router/metrics`` (gzip'd
OpenMetrics) holds only ``zenoh_build_info`` (Zenoh's ``stats`` feature, whose counters
would be there, is not compiled in), and ``@/<zid>/**`` lists sessions, links and link
states. Bytes on the wire are counted outside Zenoh, by the kernel (``bench --fleet``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any, TextIO

import zenoh

from epc_offboard.common.errors import EXIT_OK, EXIT_RUNTIME, UsageError
from epc_offboard.common.procstats import process_report

STATS_KEY = "epc/router/{zid}/stats"

# Zenoh's log targets whose lines are refusals, and the level each needs (see the docstring;
# zenoh 1.10: io/zenoh-links/zenoh-link-tls/src/unicast.rs, io/zenoh-transport/src/unicast/
# establishment/accept.rs and ext/auth/usrpwd.rs)
_LOG_FILTER = "warn,zenoh_transport::unicast::establishment=debug"
_REFUSALS = (  # (counter, pattern in a log line), first match wins
    ("tls_refused", re.compile(r"zenoh_link_tls.*(certificate|Certificate|handshake|TLS)")),
    ("auth_refused", re.compile(r"UsrPwd extension.*(Invalid|Expected|mismatch|failed)",
                                re.IGNORECASE)),
)  # fmt: skip
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_PASS_LOG_EVERY_S = 1.0  # refusal lines passed to stderr at most this often (a flood is counted)


def parse_cfg(item: str) -> tuple[str, str]:
    """``PATH:JSON5`` (as zenohd's ``--cfg``), e.g. ``transport/auth/usrpwd/user:"v1"``."""
    path, sep, value = item.partition(":")
    if not sep or not path or not value:
        raise UsageError(f"--cfg {item!r}: expected PATH:VALUE, e.g. 'listen/endpoints:[...]'")
    return path, value


def router_config(
    listen: Sequence[str], config_file: str | None, cfg: Sequence[tuple[str, str]],
    *, multicast: bool = False,
) -> zenoh.Config:  # fmt: skip
    """The router's Zenoh config: the file, then each ``--cfg``, then mode and endpoints."""
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    for path, value in cfg:
        try:
            conf.insert_json5(path, value)
        except Exception as exc:  # zenoh raises its own error type for an unknown key
            raise UsageError(f"--cfg {path}:{value}: {exc}") from exc
    conf.insert_json5("mode", '"router"')
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if not multicast:
        conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class RefusalLog:
    """Reads Zenoh's log lines from a pipe, counts refusals, passes lines on to ``out``
    (refusal lines at most once a second each kind: a flood of denials is counted, not
    printed)."""

    def __init__(self, fd: int, out: TextIO) -> None:
        self._fd = fd
        self._out = out
        self.counts: Counter[str] = Counter()
        self._passed_at: dict[str, float] = {}
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="zenoh-log", daemon=True)
        self._thread.start()

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return {name: self.counts[name] for name, _ in _REFUSALS}

    def _run(self) -> None:
        with os.fdopen(self._fd, "r", errors="replace") as fh:
            for raw in fh:
                self.feed(raw)

    def feed(self, raw: str) -> None:
        line = _ANSI.sub("", raw)
        kind = next((name for name, pat in _REFUSALS if pat.search(line)), None)
        now = time.monotonic()
        if kind is not None:
            with self._lock:
                self.counts[kind] += 1
            if now - self._passed_at.get(kind, -1e9) < _PASS_LOG_EVERY_S:
                return
            self._passed_at[kind] = now
        elif " DEBUG " in line or " TRACE " in line:
            return  # the refusal targets' other chatter
        self._out.write(line)
        self._out.flush()


class FleetRouter:
    """A Zenoh session in router mode, with its stats."""

    def __init__(self, conf: zenoh.Config, listen: Sequence[str]) -> None:
        self.listen = tuple(listen)
        self.session = zenoh.open(conf)
        self.zid = str(self.session.zid())
        self.started_s = time.monotonic()
        self.events: Counter[str] = Counter()
        self._lock = threading.Lock()
        self.refusals: RefusalLog | None = None
        self._declared: list[Any] = [
            self.session.info.declare_transport_events_listener(self._on_transport),
            self.session.declare_queryable(STATS_KEY.format(zid=self.zid), self._on_query),
        ]

    def _on_transport(self, event: zenoh.TransportEvent) -> None:
        opened = event.kind == zenoh.SampleKind.PUT
        with self._lock:
            self.events["transports_opened" if opened else "transports_closed"] += 1

    def _on_query(self, query: zenoh.Query) -> None:
        query.reply(query.key_expr, json.dumps(self.stats()))

    def stats(self) -> dict[str, Any]:
        sessions: Counter[str] = Counter(
            str(t.whatami).rsplit(".", 1)[-1].lower() for t in self.session.info.transports()
        )
        with self._lock:
            events = dict(self.events)
        proc = process_report(os.getpid())
        return {
            "zid": self.zid,
            "listen": list(self.listen),
            "uptime_s": round(time.monotonic() - self.started_s, 1),
            "sessions": {k: sessions.get(k, 0) for k in ("client", "peer", "router")},
            "transports_opened": events.get("transports_opened", 0),
            "transports_closed": events.get("transports_closed", 0),
            "refused": self.refusals.snapshot() if self.refusals is not None else {},
            "cpu_s": proc.get("cpu_s"),
            "cpu_share": proc.get("cpu_share"),
            "rss_mb": proc.get("rss_mb"),
        }

    def close(self) -> None:
        for obj in reversed(self._declared):
            obj.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]


def _zenoh_log_to_pipe() -> tuple[TextIO, int]:
    """Zenoh writes its log to fd 1: point fd 1 at a pipe (read by :class:`RefusalLog`) and
    return a stream on the original stdout, for the stats, and the pipe's reading end."""
    sys.stdout.flush()
    stats_out = os.fdopen(os.dup(1), "w", buffering=1)
    read_fd, write_fd = os.pipe()
    os.dup2(write_fd, 1)
    os.close(write_fd)
    sys.stdout = stats_out  # print() keeps going to the real stdout
    return stats_out, read_fd


def run_router_command(args: argparse.Namespace) -> int:
    listen: list[str] = list(args.listen or [])
    cfg = [parse_cfg(item) for item in (args.cfg or [])]
    for ep in listen:
        if "/" not in ep:
            raise UsageError(f"--listen {ep!r}: expected PROTOCOL/ADDRESS:PORT")
    if not listen and not args.config:
        raise UsageError("give --listen ENDPOINT (or a --config whose listen/endpoints are set)")
    stats_out, read_fd = _zenoh_log_to_pipe()
    refusals = RefusalLog(read_fd, sys.stderr)
    zenoh.init_log_from_env_or(_LOG_FILTER)
    try:
        conf = router_config(listen, args.config, cfg, multicast=args.multicast_scouting)
        router = FleetRouter(conf, listen)
    except UsageError:
        raise
    except Exception as exc:
        print(f"epc-offboard fleet router: could not open the router: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    router.refusals = refusals
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(json.dumps({"event": "started", "zid": router.zid, "listen": listen,
                      "stats_key": STATS_KEY.format(zid=router.zid)}), file=stats_out)  # fmt: skip
    try:
        while not stop.wait(args.stats_every):
            print(json.dumps({"event": "stats", **router.stats()}), file=stats_out)
    finally:
        print(json.dumps({"event": "stopped", **router.stats()}), file=stats_out)
        router.close()
    return EXIT_OK
