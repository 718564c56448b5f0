"""`epc-offboard bench --link`: what one received datagram costs the service's interpreter,
genuine and garbage, on pymavlink's parser (the receive path before issue 21) against the
header-first receive path (``vehicle/receive.py``).

Datagrams:

* genuine: the autopilot's streams as PX4 sends them to the service (ATTITUDE,
  ATTITUDE_QUATERNION, LOCAL_POSITION_NED, ODOMETRY, HEARTBEAT in the proportions of their
  rates), one frame each, realistic values;
* genuine_signed: the same, signed (MAVLink 2 signing configured on both sides);
* garbage: the fuzzer's mix (``tools/fuzz_mavlink.py``: random bytes, bad CRCs, MAVLink 1,
  unknown ids, other systems, the vehicle's ids with NaN or jumped stamps), also by kind.

Paths, each timed per datagram with ``perf_counter_ns`` (median, p99) and per batch (mean):

* ``old``: ``MAVLink.parse_buffer`` with robust parsing, its leftover dropped, then the old
  link's filter (BAD_DATA, UNKNOWN, system id), as main's ``MavlinkLink._on_bytes`` did;
* ``new``: ``FrameReceiver.datagram`` with the service's filters (system, component, the ids
  it reads): every datagram examined, the worst case (a flood from rotating addresses before
  the shared budget runs dry);
* ``link``: ``MavlinkLink._on_datagram`` (the per-source gate, the peer's bookkeeping, the
  callback a no-op), garbage from one address: what a single-source flood costs.

The JSON gives the machine's load and CPU count beside the figures.
"""

from __future__ import annotations

import json
import logging
import math
import os
import random
import statistics
import sys
import time
from collections import Counter
from collections.abc import Callable
from functools import partial
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from epc_offboard.common.signing import enable_signing
from epc_offboard.tools.fuzz_mavlink import Fuzzer
from epc_offboard.vehicle.link import MavlinkLink
from epc_offboard.vehicle.receive import SERVICE_MESSAGE_IDS, FrameReceiver

# genuine messages per second in PX4's onboard streams once the service has asked for them
_GENUINE_MIX = {
    "ATTITUDE": 100,
    "ATTITUDE_QUATERNION": 200,
    "LOCAL_POSITION_NED": 100,
    "ODOMETRY": 30,
    "HEARTBEAT": 1,
}
_AUTOPILOT = ("127.0.0.1", 14580)
_FUZZER = ("127.0.0.1", 40000)
_KEY = bytes(range(32))


def genuine_datagrams(n: int, seed: int = 0, key: bytes | None = None) -> list[bytes]:
    """``key``: signed with it (each frame a newer timestamp, as the autopilot signs)."""
    rng = random.Random(seed)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    if key is not None:
        enable_signing(mav, key)
    kinds = list(_GENUINE_MIX)
    weights = list(_GENUINE_MIX.values())
    out = []
    for i in range(n):
        t_ms = 60_000 + i
        r = [rng.uniform(-0.2, 0.2) for _ in range(6)]
        kind = rng.choices(kinds, weights)[0]
        if kind == "ATTITUDE":
            msg = mav.attitude_encode(t_ms, *r)
        elif kind == "ATTITUDE_QUATERNION":
            msg = mav.attitude_quaternion_encode(t_ms, 1.0, r[0] / 10, r[1] / 10, r[2], *r[3:])
        elif kind == "LOCAL_POSITION_NED":
            msg = mav.local_position_ned_encode(t_ms, r[0], r[1], -2.5 + r[2], *r[3:])
        elif kind == "ODOMETRY":
            msg = mav.odometry_encode(
                t_ms * 1000, 1, 12, r[0], r[1], -2.5, [1.0, 0.0, 0.0, r[2]], *r[3:], *r[:3],
                [math.nan] + [0.0] * 20, [math.nan] + [0.0] * 20,
            )  # fmt: skip
        else:
            msg = mav.heartbeat_encode(2, 12, 157, 6 << 16, 4)
        out.append(bytes(msg.pack(mav)))
    return out


def garbage_datagrams(n: int, seed: int = 0) -> list[tuple[str, bytes]]:
    fuzzer = Fuzzer(seed)
    return [fuzzer.datagram() for _ in range(n)]


def _old_path(key: bytes | None = None) -> Callable[[bytes], int]:
    mav = mavlink.MAVLink(None, srcSystem=245, srcComponent=191)
    mav.robust_parsing = True
    if key is not None:
        enable_signing(mav, key)
    accept = frozenset({1})

    def receive(data: bytes) -> int:
        n = 0
        for msg in mav.parse_buffer(data) or []:
            mtype = msg.get_type()
            if mtype == "BAD_DATA" or mtype.startswith("UNKNOWN"):
                continue
            if msg.get_srcSystem() not in accept:
                continue
            n += 1
        if mav.buf_len() > 0:
            mav.buf = bytearray()
            mav.buf_index = 0
            mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        return n

    return receive


def _new_path(key: bytes | None = None) -> Callable[[bytes], Any]:
    rx = FrameReceiver(
        Counter(),
        accept_ids=SERVICE_MESSAGE_IDS,
        accept_systems=frozenset({1}),
        accept_components=frozenset({1}),
        signature=None if key is None else enable_signing(mavlink.MAVLink(None), key),
        decode_other=mavlink.MAVLink(None).decode,
    )
    return rx.datagram


def _link_path(source: tuple[str, int], key: bytes | None = None) -> Callable[[bytes], None]:
    link = MavlinkLink(
        "udpin://127.0.0.1:0", system_id=245, component_id=191, on_message=lambda _m: None,
        accept_system_ids=frozenset({1}), accept_component_ids=frozenset({1}),
        accept_message_ids=SERVICE_MESSAGE_IDS, signing_key=key,
    )  # fmt: skip
    # the autopilot is the link's peer, as it is in flight (signed: its first frame makes it
    # so, since a frame signed now would make the stream's older frames replays)
    if key is None:
        link._on_datagram(genuine_datagrams(1, seed=1)[0], _AUTOPILOT)

    def receive(data: bytes) -> None:
        link._on_datagram(data, source)

    return receive


def _time(
    make: Callable[[], Callable[[bytes], Any]], datagrams: list[bytes], repeats: int
) -> dict[str, float]:
    """Each repeat on a path made afresh (a signed stream's replay state starts clean)."""
    per: list[float] = []
    means: list[float] = []
    clock = time.perf_counter_ns
    for _ in range(repeats):
        fn = make()
        t_batch = time.perf_counter()
        for d in datagrams:
            t0 = clock()
            fn(d)
            per.append((clock() - t0) * 1e-3)
        means.append((time.perf_counter() - t_batch) / len(datagrams) * 1e6)
    per.sort()
    return {
        "median_us": statistics.median(per),
        "p99_us": per[min(len(per) - 1, int(0.99 * len(per)))],
        "mean_us": min(means),  # the batch least disturbed by the machine's other work
    }


def run_link_bench(n: int = 20_000, repeats: int = 3) -> dict[str, Any]:
    genuine = genuine_datagrams(n)
    garbage = garbage_datagrams(n)
    garbage_bytes = [d for _, d in garbage]
    load_before = os.getloadavg()
    report: dict[str, Any] = {
        "datagrams": n,
        "repeats": repeats,
        "cpus": os.cpu_count(),
        "python": sys.version.split()[0],
        "streams": {},
    }
    sets = {
        "genuine": (genuine, None),
        "garbage": (garbage_bytes, None),
        "genuine_signed": (genuine_datagrams(n, seed=2, key=_KEY), _KEY),
    }
    for name, (data, key) in sets.items():
        source = _FUZZER if name == "garbage" else _AUTOPILOT
        row: dict[str, Any] = {
            "old": _time(partial(_old_path, key), data, repeats),
            "new": _time(partial(_new_path, key), data, repeats),
            "link": _time(partial(_link_path, source, key), data, repeats),
        }
        row["ratio_old_new_median"] = row["old"]["median_us"] / row["new"]["median_us"]
        row["ratio_old_new_mean"] = row["old"]["mean_us"] / row["new"]["mean_us"]
        report["streams"][name] = row
    by_kind: dict[str, dict[str, float]] = {}
    for kind in Fuzzer.KINDS:
        data = [d for k, d in garbage if k == kind]
        old, new = _time(_old_path, data, 1), _time(_new_path, data, 1)
        by_kind[kind] = {
            "old_median_us": old["median_us"],
            "new_median_us": new["median_us"],
            "ratio": old["median_us"] / new["median_us"],
        }
    report["garbage_by_kind"] = by_kind
    report["load_avg_1_5_15"] = [round((a + b) / 2, 2) for a, b in zip(
        load_before, os.getloadavg(), strict=True)]  # fmt: skip
    return report


def format_report(report: dict[str, Any]) -> str:
    lines = [
        f"per-datagram receive cost, us ({report['datagrams']} datagrams x "
        f"{report['repeats']}; load {report['load_avg_1_5_15'][0]} on {report['cpus']} CPUs)",
        f"{'':10} {'path':5} {'median':>8} {'p99':>8} {'mean':>8}",
    ]
    for name, row in report["streams"].items():
        for path in ("old", "new", "link"):
            t = row[path]
            lines.append(
                f"{name:10} {path:5} {t['median_us']:8.2f} {t['p99_us']:8.2f} {t['mean_us']:8.2f}"
            )
        lines.append(
            f"{name:10} old/new: {row['ratio_old_new_median']:.1f}x (median), "
            f"{row['ratio_old_new_mean']:.1f}x (mean)"
        )
    lines.append("garbage by kind (median us): " + ", ".join(
        f"{k} {v['old_median_us']:.1f} -> {v['new_median_us']:.1f}"
        for k, v in report["garbage_by_kind"].items()))  # fmt: skip
    return "\n".join(lines)


def run_link_bench_command(json_path: str | None, n: int = 20_000) -> int:
    # the fuzz makes the link warn (MAVLink 1 frames): the figures are the output here
    logging.getLogger("epc_offboard.vehicle.link").setLevel(logging.ERROR)
    report = run_link_bench(n)
    print(format_report(report))
    if json_path:
        with open(json_path, "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=2)
            fh.write("\n")
    return 0
