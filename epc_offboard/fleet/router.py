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
the stats. Messages an access rule denies are counted the same way, when the config enables
``access_control``: Zenoh 1.10 (the pip build) logs every access decision at TRACE
(``zenoh::net::routing::interceptor::access_control``): a message whose key expression has
no cached decision as ``... is unauthorized to Put (ingress) on KEY``, one on a declared key
expression as ``Using cached result: ... is unauthorized to ...``, one line a message
(measured: 5 forged puts, 5 lines, either way). Declaring a key expression computes its
cache: one line for every message kind in both flows, none of them a message; such a burst
(an uncached ``Query (ingress)`` then ``Reply (ingress)`` on one key, on one thread) is not
counted. Counted by kind: ``acl_denied_put``, ``_delete``, ``_query``, ``_reply``,
``_declare`` (subscribers, queryables, liveliness), egress denials with ingress ones. The
cost: a line per message routed (allowed ones too) read by this process (9 us of CPU each
to parse here, measured; Zenoh's formatting not included). Nor does the
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

from epc_offboard.common.children import die_with_launcher
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
_ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
_ACL_FILTER = f",{_ACL_TARGET}=trace"  # every access decision (see the docstring)
_ACL_LINE = re.compile(
    r"ThreadId\((?P<thread>\d+)\).*?(?P<cached>Using cached result: )?\S+ (?:on \S+ )?"
    r"is (?P<un>un)?authorized to (?P<what>.+?) \((?P<flow>ingress|egress)\) on (?P<key>\S+)"
)
_ACL_KINDS = {"Put": "put", "Delete": "delete", "Query": "query", "Reply": "reply"}
_ACL_PENDING_S = 0.5  # an uncached query's line, held to see whether a cache burst follows
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
        # per Zenoh thread: an uncached query's decision (key, counter or "", when), and the
        # key expression whose cache is being computed (its lines are no messages)
        self._pending: dict[str, tuple[str, str, float]] = {}
        self._burst: dict[str, str] = {}
        self._thread = threading.Thread(target=self._run, name="zenoh-log", daemon=True)
        self._thread.start()

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            now = time.monotonic()
            for thread, (_key, name, at) in list(self._pending.items()):
                if now - at > _ACL_PENDING_S:  # no burst followed: it was a query
                    del self._pending[thread]
                    self.counts[name] += bool(name)
            out = {name: self.counts[name] for name, _ in _REFUSALS}
            out.update({k: v for k, v in self.counts.items() if k.startswith("acl_denied")})
            return out

    def _acl(self, line: str, now: float) -> bool:
        """An access decision's line: counted if a message was denied; whether denied."""
        m = _ACL_LINE.search(line)
        if m is None:
            return False
        thread, key, denied = m["thread"], m["key"], bool(m["un"])
        cached, ingress = bool(m["cached"]), m["flow"] == "ingress"
        what = m["what"]
        kind = _ACL_KINDS.get(what, "declare")
        name = f"acl_denied_{kind}" if denied else ""
        with self._lock:
            if not cached and self._burst.get(thread) == key:
                return False  # a line of a key expression's cache being computed
            self._burst.pop(thread, None)
            pending = self._pending.pop(thread, None)
            if pending is not None:
                if not cached and ingress and kind == "reply" and key == pending[0]:
                    self._burst[thread] = key  # Query, Reply, ... on one key: the cache
                    return False
                self.counts[pending[1]] += bool(pending[1])
            if not cached and ingress and kind == "query":
                self._pending[thread] = (key, name, now)
            elif denied:
                self.counts[name] += 1
        return denied

    def _run(self) -> None:
        with os.fdopen(self._fd, "r", errors="replace") as fh:
            for raw in fh:
                self.feed(raw)

    def feed(self, raw: str) -> None:
        line = _ANSI.sub("", raw)
        now = time.monotonic()
        if _ACL_TARGET in line:
            if self._acl(line, now) and now - self._passed_at.get("acl", -1e9) >= 1.0:
                self._passed_at["acl"] = now  # one denial line a second reaches stderr
                self._out.write(line)
                self._out.flush()
            return
        kind = next((name for name, pat in _REFUSALS if pat.search(line)), None)
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


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def run_router_command(args: argparse.Namespace) -> int:
    # SIGINT and SIGTERM blocked in every thread (Zenoh's, the log reader) and taken by the
    # main loop's sigtimedwait: before, a handler set a threading.Event, whose lock the main
    # thread may hold in Event.wait when the signal lands (a self-deadlock: a router that
    # ignored SIGTERM outlived a dead pytest, stop 39). Blocked first, before any thread.
    signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    die_with_launcher()  # started by `sim`, a test or `bench --fleet`: SIGTERM when it dies
    listen: list[str] = list(args.listen or [])
    cfg = [parse_cfg(item) for item in (args.cfg or [])]
    for ep in listen:
        if "/" not in ep:
            raise UsageError(f"--listen {ep!r}: expected PROTOCOL/ADDRESS:PORT")
    if not listen and not args.config:
        raise UsageError("give --listen ENDPOINT (or a --config whose listen/endpoints are set)")
    try:
        conf = router_config(listen, args.config, cfg, multicast=args.multicast_scouting)
        acl = json.loads(conf.get_json("access_control/enabled") or "false") is True
    except UsageError:
        raise
    except Exception as exc:
        print(f"epc-offboard fleet router: could not read the config: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    stats_out, read_fd = _zenoh_log_to_pipe()
    refusals = RefusalLog(read_fd, sys.stderr)
    zenoh.init_log_from_env_or(_LOG_FILTER + (_ACL_FILTER if acl else ""))
    try:
        router = FleetRouter(conf, listen)
    except UsageError:
        raise
    except Exception as exc:
        print(f"epc-offboard fleet router: could not open the router: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    router.refusals = refusals
    print(json.dumps({"event": "started", "zid": router.zid, "listen": listen,
                      "stats_key": STATS_KEY.format(zid=router.zid)}), file=stats_out)  # fmt: skip
    try:
        while signal.sigtimedwait(_STOP_SIGNALS, args.stats_every) is None:
            print(json.dumps({"event": "stats", **router.stats()}), file=stats_out)
    finally:
        print(json.dumps({"event": "stopped", **router.stats()}), file=stats_out)
        router.close()
    return EXIT_OK
