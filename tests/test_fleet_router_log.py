"""The fleet router's count of access-control denials, from Zenoh's TRACE lines (issue 25):
every denied message counted once, by kind; the burst Zenoh logs when a client declares a
key expression (its cached decisions, computed for every kind and both flows: no message)
not counted. The lines are zenoh 1.10's, as a router with an ACL wrote them (the live
proof is tests/test_fleet_trust.py: 9 forged publications, 9 counted)."""

from __future__ import annotations

import io
import os

from epc_offboard.fleet.router import RefusalLog

_ZID = "99f8883b1046bbdbe7ee8a8141a09da4"
_SUBJECT = f"Interface(lo)+Transport(Tcp)+{_ZID}"


def line(thread: int, decision: str, what: str, key: str, *, cached: bool = False) -> str:
    head = (f"2026-11-26T09:38:05.794336Z TRACE rx-0 ThreadId({thread:02d}) "
            "zenoh::net::routing::interceptor::access_control: ")  # fmt: skip
    who = f"Using cached result: {_ZID}" if cached else f"{_ZID} on {_SUBJECT}"
    return f"{head}{who} is {decision} to {what} on {key}\n"


_BURST = [  # what declaring a key expression logs (zenoh 1.10, one thread, in this order)
    (f"Query ({flow})", f"Reply ({flow})", f"Put ({flow})", f"Delete ({flow})",
     f"Declare/Undeclare Subscriber ({flow})", f"Declare/Undeclare Queryable ({flow})",
     f"Declare/Undeclare Liveliness Token ({flow})", f"Liveliness Query ({flow})",
     f"Declare Liveliness Subscriber ({flow})")
    for flow in ("ingress", "egress")
]


def test_every_denied_message_is_counted_once_and_a_declarations_burst_not_at_all():
    r, w = os.pipe()
    os.close(w)
    out = io.StringIO()
    log = RefusalLog(r, out)
    forged = "epc/fleet/sig/ctl/v1"
    lines = [
        line(7, "unauthorized", "Put (ingress)", forged),  # an undeclared key: each logged
        line(8, "authorized", "Put (ingress)", "epc/fleet/sig/ctl/v3"),
        line(8, "unauthorized", "Put (ingress)", forged),
    ]
    for flow in _BURST:  # a publisher declared on the forged key: no message yet
        lines += [line(7, "unauthorized" if "Subscriber" not in what else "authorized", what,
                       forged) for what in flow]  # fmt: skip
    lines += [line(7, "unauthorized", "Put (ingress)", forged, cached=True)] * 3
    lines += [
        line(8, "unauthorized", "Query (ingress)", "epc/fleet/sig/lib/v1"),  # a real query
        line(8, "authorized", "Put (ingress)", "epc/fleet/sig/ctl/v3"),
        line(7, "unauthorized", "Put (egress)", "epc/fleet/sig/ctl/v3"),  # not delivered
        "2026-11-26T09:38:05Z WARN zenoh_link_tls: a line of another kind\n",
    ]
    for text in lines:
        log.feed(text)
    counts = log.snapshot()
    assert counts["acl_denied_put"] == 6  # 2 undeclared, 3 cached, 1 egress
    assert counts["acl_denied_query"] == 1
    assert not any(counts.get(f"acl_denied_{k}") for k in ("reply", "delete", "declare"))
    assert "another kind" in out.getvalue()  # other lines still pass to stderr
