"""What crosses from the fleet helper process to the control process: fixed-size records.

A received controller arrives in the control process already decoded and validated (by the
helper, :mod:`epc_offboard.fleet.exchange`) as one row of its ``candidate_dtype``: its active
set, importance, uses, origin and likeliest successors, padded to the problem's largest
active set. A live reference is one row of :data:`REFERENCE_DTYPE`. Counters and the
helper's heartbeat are slots of a shared int64 array (:data:`STAT_NAMES`), written by the
helper only. Pure: numpy in, numpy and tuples out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from epc_offboard.fleet.wire import (
    MAX_HORIZON_POINTS,
    ReferenceMessage,
)

ActiveSet = tuple[int, ...]
Records = npt.NDArray[Any]


@dataclass(frozen=True)
class ProblemSpec:
    """What the helper needs of one shared problem to validate what peers send for it."""

    name: str
    signature: str
    n_con: int  # constraint rows: active-set indices are below this
    max_active: int  # rows of an active set at most (the problem's n_u)
    max_entries: int  # controllers in one message at most (the library's size)


REFERENCE_DTYPE = np.dtype(
    [
        ("received_s", "f8"),  # time.monotonic() in the helper (CLOCK_MONOTONIC: one clock)
        ("pos_ned_m", "f8", (3,)),
        ("has_vel", "u1"),
        ("vel_ned_m_s", "f8", (3,)),
        ("has_yaw", "u1"),
        ("yaw_rad", "f8"),
        ("horizon_dt_s", "f8"),
        ("n_horizon", "u2"),
        ("horizon_pos_ned_m", "f8", (MAX_HORIZON_POINTS, 3)),
    ]
)


def reference_record(msg: ReferenceMessage, received_s: float) -> Records:
    rec = np.zeros(1, dtype=REFERENCE_DTYPE)
    row = rec[0]
    row["received_s"] = received_s
    row["pos_ned_m"] = msg.pos_ned_m
    if msg.vel_ned_m_s is not None:
        row["has_vel"], row["vel_ned_m_s"] = 1, msg.vel_ned_m_s
    if msg.yaw_rad is not None:
        row["has_yaw"], row["yaw_rad"] = 1, msg.yaw_rad
    if msg.horizon_pos_ned_m:
        row["horizon_dt_s"] = msg.horizon_dt_s
        row["n_horizon"] = len(msg.horizon_pos_ned_m)
        row["horizon_pos_ned_m"][: len(msg.horizon_pos_ned_m)] = msg.horizon_pos_ned_m
    return rec


def reference_of(row: Any) -> tuple[ReferenceMessage, float]:
    """A record back as (the message, when the helper received it)."""

    def vec3(a: Any) -> tuple[float, float, float]:
        x, y, z = a.tolist()
        return (x, y, z)

    n = int(row["n_horizon"])
    msg = ReferenceMessage(
        vec3(row["pos_ned_m"]),
        vec3(row["vel_ned_m_s"]) if row["has_vel"] else None,
        float(row["yaw_rad"]) if row["has_yaw"] else None,
        float(row["horizon_dt_s"]) if n else None,
        tuple(vec3(p) for p in row["horizon_pos_ned_m"][:n]),
    )
    return msg, float(row["received_s"])


# the helper's counters (and gauges), one int64 slot each in an array both processes map
STAT_NAMES = (
    "heartbeat_ns",  # time.monotonic_ns() of the helper's last turn (its liveness)
    "state",  # 0 starting, 1 session open, -1 the session could not open
    "messages_received", "own_ignored", "rejected_oversized", "fleet_rate_limited",
    "rate_limited", "rejected_malformed", "entries_received", "entries_rejected_by_problem",
    "entries_duplicate", "dropped_queue_full", "candidates_forwarded", "candidates_waiting",
    "senders", "peers", "rate_buckets", "rate_buckets_evicted",
    "entries_published", "publish_errors", "snapshots_prepared",
    "queries_sent", "queries_answered", "query_errors", "query_reply_errors",
    "references_received", "reference_rejected", "references_superseded",
    "references_forwarded",
    "tasks_dropped",
    "publish_seq_done",  # the last publish frame the helper handled (the control's number)
    "session_open_failures",  # sessions that did not open (a router's refusal among them)
    "peer_joins", "peer_leaves",  # liveliness changes (a flapping token: each counted)
    "queries_skipped",  # arrivals never queried: more were waiting than kept
    # payload bytes (+ attachments) this vehicle put, took in and answered queries with; a
    # query from a vehicle that holds everything is answered with an empty reply (up to date)
    "bytes_published", "bytes_received", "bytes_answered", "queries_up_to_date",
    "queries_repeated",  # library queries asked again: no reply came back (see session)
    "replies_up_to_date",  # empty replies taken: the peer had nothing this vehicle lacks
)  # fmt: skip
STAT_INDEX = {name: i for i, name in enumerate(STAT_NAMES)}
