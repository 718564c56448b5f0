"""The controller library and learned models on disk: SQLite in WAL mode.

Why SQLite: transactional (a kill -9 at any moment leaves a file that opens, holding every
transaction committed before the kill — WAL with synchronous=NORMAL is durable against a
process crash), readable by `epc-offboard db info` and the sqlite3 shell while the service
runs, and in the standard library.

What is stored is experience, never gains: each controller is an active set (sorted
constraint row indices of the problem) under the problem signature it belongs to, with its
importance and use count; transitions between active sets; and opaque model blobs (LWPR).
Rows are validated when read: a row that does not parse is skipped and counted, never fatal.
A file that is not a database, fails SQLite's quick_check, or has another schema version is
moved aside (``NAME.corrupt-YYYYmmddTHHMMSS``) with a log line, and a new empty store opens.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import sqlite3
import sys
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS controllers (
    signature TEXT NOT NULL,
    active_set TEXT NOT NULL,          -- JSON array of sorted constraint row indices
    importance REAL NOT NULL,
    uses INTEGER NOT NULL,
    origin TEXT NOT NULL,              -- solved | prior | shared:<vehicle>
    updated_unix_s REAL NOT NULL,
    PRIMARY KEY (signature, active_set)
);
CREATE TABLE IF NOT EXISTS transitions (
    signature TEXT NOT NULL,
    from_set TEXT NOT NULL,
    to_set TEXT NOT NULL,
    count INTEGER NOT NULL,
    PRIMARY KEY (signature, from_set, to_set)
);
CREATE TABLE IF NOT EXISTS models (
    name TEXT NOT NULL,
    signature TEXT NOT NULL,
    blob BLOB NOT NULL,
    updated_unix_s REAL NOT NULL,
    PRIMARY KEY (name, signature)
);
"""

ActiveSet = tuple[int, ...]


class StoreError(RuntimeError):
    """The library file could not be used."""


@dataclass(frozen=True)
class StoredController:
    active_set: ActiveSet
    importance: float
    uses: int
    origin: str = "solved"


def encode_active_set(active_set: Iterable[int]) -> str:
    return json.dumps(sorted(int(i) for i in active_set), separators=(",", ":"))


def decode_active_set(text: str) -> ActiveSet:
    """Parse a stored active set; ValueError unless it is a sorted list of unique ints >= 0."""
    data = json.loads(text)
    if not isinstance(data, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) for i in data
    ):
        raise ValueError(f"active set must be a list of integers, got {text[:60]!r}")
    if any(i < 0 for i in data) or any(b <= a for a, b in itertools.pairwise(data)):
        raise ValueError(f"active set must be sorted unique non-negative, got {text[:60]!r}")
    return tuple(data)


class LibraryStore:
    """One SQLite file. Thread-safe: the service calls it from a worker thread."""

    def __init__(self, path: str | Path, *, _conn: sqlite3.Connection) -> None:
        self.path = Path(path)
        self._conn = _conn
        self._lock = threading.Lock()
        self.skipped_rows = 0

    @classmethod
    def open(cls, path: str | Path) -> LibraryStore:
        """Open or create the store; a corrupt or incompatible file is moved aside first."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        try:
            return cls(p, _conn=_connect(p))
        except (sqlite3.DatabaseError, StoreError) as exc:
            aside = p.with_name(f"{p.name}.corrupt-{time.strftime('%Y%m%dT%H%M%S')}")
            log.error(
                "library %s is unusable (%s): moved aside to %s, starting empty", p, exc, aside
            )
            for suffix in ("", "-wal", "-shm"):
                side = Path(str(p) + suffix)
                if side.exists():
                    side.rename(Path(str(aside) + suffix))
            return cls(p, _conn=_connect(p))

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    def __enter__(self) -> LibraryStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- controllers -------------------------------------------------------------------

    def save_controllers(self, signature: str, entries: Iterable[StoredController]) -> int:
        """Insert or update controllers in one transaction; returns how many were written."""
        now = time.time()
        rows = [
            (
                signature,
                encode_active_set(e.active_set),
                float(e.importance),
                int(e.uses),
                e.origin,
                now,
            )
            for e in entries
        ]
        with self._lock, self._conn:
            self._conn.executemany(
                "INSERT INTO controllers VALUES (?, ?, ?, ?, ?, ?) "
                "ON CONFLICT (signature, active_set) DO UPDATE SET "
                "importance = max(importance, excluded.importance), "
                "uses = max(uses, excluded.uses), updated_unix_s = excluded.updated_unix_s",
                rows,
            )
        return len(rows)

    def load_controllers(self, signature: str) -> list[StoredController]:
        """Every valid controller of ``signature``, most important first."""
        with self._lock:
            rows = self._conn.execute(
                "SELECT active_set, importance, uses, origin FROM controllers "
                "WHERE signature = ? ORDER BY importance DESC",
                (signature,),
            ).fetchall()
        out = []
        for active_text, importance, uses, origin in rows:
            try:
                out.append(
                    StoredController(
                        decode_active_set(active_text), float(importance), int(uses), str(origin)
                    )
                )
            except (ValueError, TypeError) as exc:
                self.skipped_rows += 1
                log.warning("library %s: skipped a bad controller row: %s", self.path, exc)
        return out

    def delete_controllers(self, signature: str, active_sets: Iterable[ActiveSet]) -> None:
        with self._lock, self._conn:
            self._conn.executemany(
                "DELETE FROM controllers WHERE signature = ? AND active_set = ?",
                [(signature, encode_active_set(a)) for a in active_sets],
            )

    # -- transitions -------------------------------------------------------------------

    def save_transitions(
        self, signature: str, counts: dict[tuple[ActiveSet, ActiveSet], int]
    ) -> None:
        rows = [
            (signature, encode_active_set(a), encode_active_set(b), int(n))
            for (a, b), n in counts.items()
        ]
        with self._lock, self._conn:
            self._conn.executemany(
                "INSERT INTO transitions VALUES (?, ?, ?, ?) "
                "ON CONFLICT (signature, from_set, to_set) DO UPDATE SET count = excluded.count",
                rows,
            )

    def load_transitions(self, signature: str) -> dict[tuple[ActiveSet, ActiveSet], int]:
        with self._lock:
            rows = self._conn.execute(
                "SELECT from_set, to_set, count FROM transitions WHERE signature = ?", (signature,)
            ).fetchall()
        out: dict[tuple[ActiveSet, ActiveSet], int] = {}
        for a, b, n in rows:
            try:
                out[(decode_active_set(a), decode_active_set(b))] = int(n)
            except (ValueError, TypeError) as exc:
                self.skipped_rows += 1
                log.warning("library %s: skipped a bad transition row: %s", self.path, exc)
        return out

    # -- models ------------------------------------------------------------------------

    def save_model(self, name: str, signature: str, blob: bytes) -> None:
        with self._lock, self._conn:
            self._conn.execute(
                "INSERT INTO models VALUES (?, ?, ?, ?) ON CONFLICT (name, signature) "
                "DO UPDATE SET blob = excluded.blob, updated_unix_s = excluded.updated_unix_s",
                (name, signature, sqlite3.Binary(blob), time.time()),
            )

    def load_model(self, name: str, signature: str) -> bytes | None:
        with self._lock:
            row = self._conn.execute(
                "SELECT blob FROM models WHERE name = ? AND signature = ?", (name, signature)
            ).fetchone()
        return None if row is None else bytes(row[0])

    # -- inspection ----------------------------------------------------------------------

    def summary(self) -> dict[str, dict[str, int]]:
        """Per signature: controllers, transitions and models stored."""
        out: dict[str, dict[str, int]] = {}
        with self._lock:
            for table, key in (
                ("controllers", "controllers"),
                ("transitions", "transitions"),
                ("models", "models"),
            ):
                for sig, n in self._conn.execute(
                    f"SELECT signature, count(*) FROM {table} GROUP BY signature"
                ):
                    out.setdefault(str(sig), {"controllers": 0, "transitions": 0, "models": 0})[
                        key
                    ] = int(n)
        return out


def _connect(path: Path) -> sqlite3.Connection:
    conn = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
    try:
        conn.execute("PRAGMA busy_timeout = 2000")
        conn.execute("PRAGMA journal_mode = WAL")
        conn.execute("PRAGMA synchronous = NORMAL")
        check = conn.execute("PRAGMA quick_check").fetchone()
        if check is None or check[0] != "ok":
            raise StoreError(f"quick_check failed: {check}")
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if tables and "meta" not in tables:
            raise StoreError("not an epc-offboard library (no meta table)")
        if "meta" in tables:
            row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            if row is None or row[0] != str(SCHEMA_VERSION):
                raise StoreError(
                    f"schema version {row[0] if row else None}, expected {SCHEMA_VERSION}"
                )
        conn.executescript("BEGIN;" + _SCHEMA + "COMMIT;")
        conn.execute(
            "INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),)
        )
        # Python's sqlite3 with isolation_level=None is in autocommit; `with conn:` below
        # still wraps each batch in one transaction.
        conn.isolation_level = "DEFERRED"
    except Exception:
        conn.close()
        raise
    return conn


def run_db_command(args: argparse.Namespace) -> int:
    """`epc-offboard db info PATH`: what a library file holds, per problem signature."""
    from epc_offboard.errors import EXIT_OK, EXIT_RUNTIME, UsageError

    if args.action != "info":
        print(f"epc-offboard db {args.action}: not implemented yet", file=sys.stderr)
        return EXIT_RUNTIME
    if len(args.paths) != 1:
        raise UsageError("usage: epc-offboard db info LIBRARY.sqlite")
    path = Path(args.paths[0])
    if not path.exists():
        raise UsageError(f"{path}: no such library file")
    with LibraryStore.open(path) as store:
        summary = store.summary()
    print(f"{path}: schema {SCHEMA_VERSION}, {len(summary)} problem signature(s)")
    for sig, counts in sorted(summary.items()):
        print(
            f"  {sig}: {counts['controllers']} controllers, "
            f"{counts['transitions']} transitions, {counts['models']} models"
        )
    return EXIT_OK
