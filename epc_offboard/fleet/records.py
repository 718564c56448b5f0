"""What crosses from the fleet helper process to the control process: fixed-size records.

A received controller arrives in the control process already decoded and validated (by the
helper, :mod:`epc_offboard.fleet.session`) as one row of :func:`candidate_dtype`: its active
set, importance, uses, origin and likeliest successors, padded to the problem's largest
active set. A live reference is one row of :data:`REFERENCE_DTYPE`. Counters and the
helper's heartbeat are slots of a shared int64 array (:data:`STAT_NAMES`), written by the
helper only. Pure: numpy in, numpy and tuples out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from epc_offboard.control.library import LibraryEntry
from epc_offboard.fleet.wire import (
    MAX_HORIZON_POINTS,
    MAX_VEHICLE_ID_LEN,
    ControllerMessage,
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


def candidate_dtype(max_active: int, max_successors: int) -> np.dtype[Any]:
    """One received controller: ``active[:n_active]`` is its active set; successor ``k`` is
    ``successors[k, :successor_len[k]]`` for ``k < n_successors``."""
    return np.dtype(
        [
            ("problem", "u1"),  # index into the shared problems
            ("n_active", "u2"),
            ("n_successors", "u1"),
            ("importance", "f8"),
            ("uses", "u4"),
            ("origin", f"S{MAX_VEHICLE_ID_LEN}"),  # the sender's vehicle id (ASCII, checked)
            ("active", "u2", (max_active,)),
            ("successor_len", "u2", (max_successors,)),
            ("successors", "u2", (max_successors, max_active)),
        ]
    )


def candidate_records(
    msg: ControllerMessage,
    problem: int,
    dtype: np.dtype[Any],
    successors: Mapping[ActiveSet, Sequence[ActiveSet]],
) -> Records:
    """``msg``'s entries as records, the sender's least used first (a peer past its pool
    quota keeps its most used, offered last)."""
    entries = sorted(msg.entries, key=lambda e: (e.uses, e.importance))
    out = np.zeros(len(entries), dtype=dtype)
    max_succ = dtype["successor_len"].shape[0]
    out["problem"] = problem
    out["origin"] = msg.vehicle_id.encode()
    for i, e in enumerate(entries):
        row = out[i]
        row["n_active"] = len(e.active_set)
        row["active"][: len(e.active_set)] = e.active_set
        row["importance"] = e.importance
        row["uses"] = e.uses
        succ = list(successors.get(e.active_set, ()))[:max_succ]
        row["n_successors"] = len(succ)
        for k, s in enumerate(succ):
            row["successor_len"][k] = len(s)
            row["successors"][k, : len(s)] = s
    return out


def candidate_of(row: Any) -> tuple[LibraryEntry, str, tuple[ActiveSet, ...]]:
    """A record back as (entry, origin ``shared:<vehicle>``, successors)."""
    n = int(row["n_active"])
    active = tuple(row["active"][:n].tolist())
    lens = row["successor_len"].tolist()
    succ = tuple(
        tuple(row["successors"][k, : lens[k]].tolist()) for k in range(int(row["n_successors"]))
    )
    entry = LibraryEntry(active, float(row["importance"]), int(row["uses"]))
    return entry, f"shared:{row['origin'].decode()}", succ


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
    # query from a vehicle that holds everything is answered with nothing (up to date)
    "bytes_published", "bytes_received", "bytes_answered", "queries_up_to_date",
)  # fmt: skip
STAT_INDEX = {name: i for i, name in enumerate(STAT_NAMES)}
