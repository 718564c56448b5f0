"""Hostile fleet peers (issue 21's attacks), one attack per process, each a real Zenoh session
on loopback (multicast scouting off, an explicit endpoint).

``python -m epc_offboard.tools.zenoh_attack KIND --connect tcp/127.0.0.1:P --fleet F
--config SERVICE.toml [--rate 1000] [--duration 10]``

Kinds (``RATE`` a second, for ``DURATION`` seconds):

* ``flood``: well-formed, useless batches (400 controllers of random constraint rows, the
  most a message may hold) from one vehicle id;
* ``rotate``: the same from 100 vehicle ids in turn (every id gets a fresh token bucket);
* ``replay``: genuine controllers of the victim's problem, solved here as a fleet peer
  would have (valid: each passes the KKT check), recorded once as 8 peers' libraries (up to
  400 controllers each), and the same bytes sent again and again;
* ``flap``: liveliness tokens of rotating peer ids declared and undeclared (``RATE`` changes
  a second): every arrival asks the victim to query that peer's library, which nobody
  answers.

The victim's problem (signature, constraint rows) comes from its service config, as a peer
running the same configuration knows it. Everything is prepared before the session opens
(the attacker's own CPU is not what is measured). Then ``ready`` is printed; a line on stdin
starts the attack, which ends with a JSON summary on stdout. EOF on stdin ends the process.
"""

from __future__ import annotations

import argparse
import collections
import json
import random
import sys
import time
from typing import Any

import numpy as np

KINDS = ("flood", "rotate", "replay", "flap")
ROTATING_IDS = 100
FLOOD_ENTRIES = 400  # the position library's size: the most one message may carry
REPLAY_PEERS = 8
REPLAY_SOLVES = 1200
FLAP_IDS = 1000
FLAP_HELD = 16  # tokens alive at once: each change declares one and undeclares the oldest


def _problem(config_path: str) -> Any:
    """The victim's position problem, built from its config as the service builds it."""
    from epc_offboard.control.cascade import Cascade
    from epc_offboard.service.config import load_service_config

    cfg = load_service_config(config_path)
    period_s = 1.0 / cfg.loops.position_rate_hz
    return Cascade(cfg.position, cfg.attitude, cfg.estimator, period_s).position.problem


def _key(fleet: str, signature: str, vid: str) -> str:
    return f"epc/{fleet}/{signature}/ctl/{vid}"


Payloads = list[tuple[str, bytes]]  # (key, payload)


def useless_batches(fleet: str, problem: Any, ids: list[str], seed: int = 0) -> Payloads:
    """One batch per id of FLOOD_ENTRIES random (decodable, useless) active sets."""
    from epc_offboard.control.library_types import LibraryEntry
    from epc_offboard.fleet.wire import ControllerMessage, MessageKind, encode_controllers

    rng = random.Random(seed)
    sig, rows = problem.signature(), min(12, problem.n_u)
    out = []
    for vid in ids:
        chunk = tuple(
            LibraryEntry(tuple(sorted(rng.sample(range(problem.n_con), rows))))
            for _ in range(FLOOD_ENTRIES)
        )
        msg = ControllerMessage(MessageKind.BATCH, sig, vid, chunk)
        out.append((_key(fleet, sig, vid), encode_controllers(msg)))
    return out


def genuine_batches(fleet: str, problem: Any, seed: int = 0) -> Payloads:
    """REPLAY_PEERS batches of valid controllers: full QP solves at random states (position,
    velocity, acceleration within a few units of hover), each optimal where it was solved."""
    from epc_offboard.control.epc import ExperienceController
    from epc_offboard.control.library_types import LibraryEntry
    from epc_offboard.fleet.wire import ControllerMessage, MessageKind, encode_controllers

    ctl = ExperienceController(problem, max_size=REPLAY_SOLVES)
    rng = np.random.default_rng(seed)
    refs = np.zeros((problem.horizon, problem.nx))
    found: dict[tuple[int, ...], LibraryEntry] = {}
    for _ in range(REPLAY_SOLVES):
        x0 = rng.uniform(-3.0, 3.0, problem.nx)
        entry = ctl.learn(x0, refs)
        if entry is not None:
            found[entry.active_set] = LibraryEntry(entry.active_set, 1.0, 1)
    entries = list(found.values())
    sig = problem.signature()
    out = []
    for k in range(REPLAY_PEERS):
        vid = f"peer{k}"
        # each peer's whole library, as it would answer a late joiner: as many as one
        # message may carry, overlapping between peers (they fly the same problem)
        first = k * len(entries) // REPLAY_PEERS
        chunk = tuple((entries[first:] + entries[:first])[:FLOOD_ENTRIES])
        msg = ControllerMessage(MessageKind.BATCH, sig, vid, chunk)
        out.append((_key(fleet, sig, vid), encode_controllers(msg)))
    return out


def _session(connect: str) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def _paced(rate_per_s: float, duration_s: float) -> Any:
    """Yields the step number at ``rate_per_s`` for ``duration_s`` (catching up after a late
    wake-up, so the rate is the rate)."""
    t0 = time.monotonic()
    k = 0
    while time.monotonic() - t0 < duration_s:
        yield k
        k += 1
        time.sleep(max(0.0, t0 + k / rate_per_s - time.monotonic()))


def attack(
    session: Any, kind: str, fleet: str, signature: str, payloads: Payloads,
    rate_per_s: float, duration_s: float,
) -> dict[str, Any]:  # fmt: skip
    """Run one attack on an open session; returns what was sent."""
    t0 = time.monotonic()
    sent = 0
    if kind == "flap":
        tokens: collections.deque[Any] = collections.deque()
        prefix = f"epc/{fleet}/{signature}/alive"
        for k in _paced(rate_per_s, duration_s):
            if len(tokens) >= FLAP_HELD:
                tokens.popleft().undeclare()
            tokens.append(session.liveliness().declare_token(f"{prefix}/flap{k % FLAP_IDS}"))
            sent += 1
        for token in tokens:
            token.undeclare()
    else:
        for k in _paced(rate_per_s, duration_s):
            session.put(*payloads[k % len(payloads)])
            sent += 1
    elapsed = time.monotonic() - t0
    return {"kind": kind, "sent": sent, "start_monotonic_s": t0, "duration_s": elapsed,
            "rate_per_s": sent / elapsed if elapsed > 0 else 0.0}  # fmt: skip


def prepare(kind: str, fleet: str, problem: Any) -> Payloads:
    if kind == "flood":
        return useless_batches(fleet, problem, ["attacker"])
    if kind == "rotate":
        return useless_batches(fleet, problem, [f"attacker{i}" for i in range(ROTATING_IDS)])
    if kind == "replay":
        return genuine_batches(fleet, problem)
    return []


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("kind", choices=KINDS)
    parser.add_argument("--connect", required=True, help="the victim's Zenoh endpoint")
    parser.add_argument("--fleet", required=True)
    parser.add_argument("--config", required=True, help="the victim's service config")
    parser.add_argument("--rate", type=float, default=1000.0, help="messages (changes) a second")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per attack")
    args = parser.parse_args(argv)
    problem = _problem(args.config)
    payloads = prepare(args.kind, args.fleet, problem)
    with _session(args.connect) as session:
        print("ready", flush=True)
        for _line in sys.stdin:  # one attack per line, until EOF
            summary = attack(session, args.kind, args.fleet, problem.signature(), payloads,
                             args.rate, args.duration)  # fmt: skip
            summary["payloads"] = len(payloads)
            print(json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
