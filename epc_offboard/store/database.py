"""The controller library and learned models on disk: SQLite in WAL mode.

Why SQLite: transactional (a kill -9 at any moment leaves a file that opens, holding every
transaction committed before the kill — WAL with synchronous=NORMAL is durable against a
process crash), readable by `epc-offboard db info` and the sqlite3 shell while the service
runs, and in the standard library.

What is stored is experience, never gains: each controller is an active set (sorted
constraint row indices of the problem) under the problem signature it belongs to, with its
importance and use count; transitions between active sets; and opaque model blobs (LWPR).
Rows are validated when read: a row that does not parse is skipped and counted, never fatal.
A file that is not a database or fails SQLite's quick_check is corrupt: the service moves it
aside (``NAME.corrupt-YYYYmmddTHHMMSS``) with a log line, and a new empty store opens. A path
that cannot be a library is refused, nothing moved (:class:`StoreRefusedError`,
:func:`library_refusal`): a directory, a parent that is a file, a directory this user cannot
write, a read-only filesystem, a symlink to nothing, another application's SQLite file, a
library of another schema version (a newer release's, which an older one must not destroy).

Offline transfer between vehicles (``epc-offboard db``, :mod:`epc_offboard.tools.db`) reads a whole
library as a :class:`LibrarySnapshot` and writes one back in a single transaction, so an
import either lands whole or not at all. Writing is idempotent: a controller or transition
already present keeps the larger importance, use count and transition count.
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path

from epc_offboard.common.errors import EpcError
from epc_offboard.control.library_types import (
    ActiveSet,
    DeferredBlob,
    DeferredText,
    LibraryEntry,
    LibrarySnapshot,
    SignatureSnapshot,
    Transition,
    blob_bytes,
    parse_active_set,
    text_of,
)

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

_TABLES = frozenset({"meta", "controllers", "transitions", "models"})
_LOOP_KEY = "loop:"  # meta rows "loop:SIGNATURE" -> "position" | "attitude"
_FLEET_KEY = "fleet:"  # meta rows "fleet:NAME" -> the fleet's state (LibrarySnapshot.fleet)
_SET_VERSION = f"INSERT OR IGNORE INTO meta VALUES ('schema_version', '{SCHEMA_VERSION}');"

_UPSERT_MODEL = (
    "INSERT INTO models VALUES (?, ?, ?, ?) ON CONFLICT (name, signature) "
    "DO UPDATE SET blob = excluded.blob, updated_unix_s = excluded.updated_unix_s"
)


class StoreError(EpcError, RuntimeError):
    """The library file could not be used."""


class StoreRefusedError(StoreError):
    """The path cannot hold this service's library and nothing there is moved or written:
    the user's mistake (a directory, another application's file, ...), not corruption."""


# SQLite's answers that say the path, not the file's content, is unusable
_PATH_ERRORS = frozenset({"SQLITE_CANTOPEN", "SQLITE_READONLY", "SQLITE_PERM", "SQLITE_AUTH"})


def path_refusal(path: str | Path) -> str | None:
    """Why ``path`` cannot hold a library, found without writing anything, or None: a
    directory or another non-file there, a symlink to nothing, an ancestor that is a file,
    a read-only filesystem, a directory or file this user may not write."""
    p = Path(path).absolute()
    if p.is_symlink() and not p.exists():
        return f"a symlink to {os.readlink(p)}, which does not exist"
    if p.exists() and not p.is_file():
        return "is a directory, not a library file" if p.is_dir() else "is not a regular file"
    ancestor = p.parent
    while not ancestor.exists() and not ancestor.is_symlink():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        return f"{ancestor} is not a directory"
    if os.statvfs(ancestor).f_flag & os.ST_RDONLY:
        return f"{ancestor} is on a read-only filesystem"
    if not os.access(ancestor, os.W_OK | os.X_OK):
        return f"directory {ancestor} is not writable by this user (uid {os.getuid()})"
    if p.exists() and not os.access(p, os.R_OK | os.W_OK):
        return f"not readable and writable by this user (uid {os.getuid()})"
    return None


def library_refusal(path: str | Path) -> str | None:
    """Why the service must refuse ``path`` as its library (:func:`path_refusal`, or a file
    that is another application's SQLite or a library of another schema version), read
    without writing; None when it can open it: a missing or empty file, a library, or a
    corrupt file (which :meth:`LibraryStore.open` moves aside)."""
    reason = path_refusal(path)
    p = Path(path)
    if reason is not None or not p.is_file() or p.stat().st_size == 0:
        return reason
    # immutable: no -wal/-shm made beside it, when there is no -wal to read
    uri = p.resolve().as_uri() + "?mode=ro" + ("" if Path(f"{p}-wal").exists() else "&immutable=1")
    try:
        conn = sqlite3.connect(uri, uri=True)
    except sqlite3.DatabaseError:
        return None  # the read-write open says why
    try:
        # judged as the read-write open judges it: a creation cut short is finished there
        return _not_ours(conn, _tables(conn), readonly=False)[0]
    except sqlite3.DatabaseError:
        return None  # corrupt: moved aside by the open
    finally:
        conn.close()


def _tables(conn: sqlite3.Connection) -> set[str]:
    return {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}


def _not_ours(conn: sqlite3.Connection, tables: set[str], *,
              readonly: bool) -> tuple[str | None, bool]:  # fmt: skip
    """Why an opened SQLite file with ``tables`` is not this release's library (another
    application's file, another schema version), or None; and whether it is a library whose
    creation was cut short (:func:`_creation_cut_short`: finished read-write, read as empty
    read-only). A file with no tables is neither (a creation killed before its first)."""
    if tables and "meta" not in tables:
        return _foreign(tables), False
    if "meta" not in tables:
        return None, False
    row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
    if row is None and _creation_cut_short(conn, tables, readonly=readonly):
        return None, True
    if row is None or row[0] != str(SCHEMA_VERSION):
        return _other_version(row), False
    return None, False


def _foreign(tables: set[str]) -> str:
    return (f"not an epc-offboard library (no meta table; its tables: "
            f"{', '.join(sorted(tables)) or 'none'})")  # fmt: skip


def _other_version(row: tuple[str] | None) -> str:
    return (f"a library of schema version {row[0] if row else None}, this release reads "
            f"{SCHEMA_VERSION}")  # fmt: skip


def store_path_refused(where: str | Path, path: str | Path, reason: str) -> str:
    """The message of a ``store.path`` refused (exit code 2): where the path came from (the
    config file, ``--out DIR``), the key, the path and why; the reason's own copy of the
    path dropped."""
    reason = reason.removeprefix(f"{path}: ")
    return f"{where}: `store.path` {path}: {reason} (nothing was moved or written)"


def encode_active_set(active_set: Iterable[int]) -> str:
    return json.dumps(sorted(int(i) for i in active_set), separators=(",", ":"))


def decode_active_set(text: str) -> ActiveSet:
    """Parse a stored active set; ValueError unless it is a sorted list of unique ints >= 0
    (:func:`~epc_offboard.control.library_types.parse_active_set`)."""
    return parse_active_set(json.loads(text))


class LibraryStore:
    """One SQLite file. Thread-safe: the service calls it from a worker thread."""

    def __init__(self, path: str | Path, *, _conn: sqlite3.Connection) -> None:
        self.path = Path(path)
        self._conn = _conn
        self._lock = threading.Lock()
        self.skipped_rows = 0

    @classmethod
    def open(cls, path: str | Path, *, repair: bool = True) -> LibraryStore:
        """Open or create the store.

        :class:`StoreRefusedError` when the path cannot hold a library (:func:`path_refusal`,
        another application's SQLite file, another schema version): nothing moved. A corrupt
        file is moved aside and a new one started when ``repair`` (the service: it must fly);
        otherwise :class:`StoreError` names the problem and the file is left as it is (the
        offline tools: a user's file is never moved under them).
        """
        p = Path(path)
        reason = library_refusal(p)  # read first: a refused file gets no -wal or -shm
        if reason is not None:
            raise StoreRefusedError(f"{p}: {reason}")
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreRefusedError(f"{p}: cannot create {p.parent}: {exc.strerror}") from exc
        try:
            return cls(p, _conn=_connect(p))
        except StoreRefusedError as exc:
            raise StoreRefusedError(f"{p}: {exc}") from exc
        except sqlite3.DatabaseError as exc:
            if getattr(exc, "sqlite_errorname", "") in _PATH_ERRORS:
                raise StoreRefusedError(f"{p}: cannot open or write it: {exc}") from exc
            if not repair:
                raise StoreError(f"{p}: not a usable library: {exc}") from exc
            failure: Exception = exc
        except StoreError as exc:
            if not repair:
                raise StoreError(f"{p}: not a usable library: {exc}") from exc
            failure = exc
        aside = p.with_name(f"{p.name}.corrupt-{time.strftime('%Y%m%dT%H%M%S')}")
        log.error("library %s is corrupt (%s): moved aside to %s, starting empty", p, failure,
                  aside)  # fmt: skip
        for suffix in ("", "-wal", "-shm"):
            side = Path(str(p) + suffix)
            if side.exists():
                side.rename(Path(str(aside) + suffix))
        return cls(p, _conn=_connect(p))

    @classmethod
    def open_readonly(cls, path: str | Path, *, immutable: bool = False) -> LibraryStore:
        """Open an existing library for reading only; :class:`StoreError` if it is unusable.

        ``immutable``: SQLite's ``immutable=1``, which creates no ``-wal``/``-shm`` beside
        the file but ignores any WAL and any concurrent writer: only for a file no process
        has open (no ``-wal`` beside it); :func:`epc_offboard.tools.db.read_library` checks that.
        """
        p = Path(path)
        if not p.is_file():
            reason = path_refusal(p) if p.exists() or p.is_symlink() else None
            raise StoreError(f"{p}: {reason or 'no such library file'}")
        try:
            return cls(p, _conn=_connect(p, readonly=True, immutable=immutable))
        except StoreRefusedError as exc:
            raise StoreRefusedError(f"{p}: {exc}") from exc
        except (sqlite3.DatabaseError, StoreError) as exc:
            raise StoreError(f"{p}: not a usable library: {exc}") from exc

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    def __enter__(self) -> LibraryStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- controllers -------------------------------------------------------------------

    def save_controllers(self, signature: str, entries: Iterable[LibraryEntry]) -> int:
        """Insert or update controllers in one transaction; returns how many were written.
        An entry that does not know its origin is stored as this vehicle's own ("solved")."""
        now = time.time()
        rows = [
            (
                signature,
                encode_active_set(e.active_set),
                float(e.importance),
                int(e.uses),
                e.origin or "solved",
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

    def load_controllers(self, signature: str) -> list[LibraryEntry]:
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
                    LibraryEntry(
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

    def save_model(self, name: str, signature: str, blob: bytes | DeferredBlob) -> None:
        """``blob``, or what builds it (built here, before the transaction)."""
        blob = blob_bytes(blob)
        with self._lock, self._conn:
            self._conn.execute(_UPSERT_MODEL, (name, signature, sqlite3.Binary(blob), time.time()))

    def load_model(self, name: str, signature: str) -> bytes | None:
        with self._lock:
            row = self._conn.execute(
                "SELECT blob FROM models WHERE name = ? AND signature = ?", (name, signature)
            ).fetchone()
        return None if row is None else bytes(row[0])

    # -- whole library (offline transfer) ------------------------------------------------

    def signatures(self) -> list[str]:
        with self._lock:
            rows = self._conn.execute(
                "SELECT signature FROM controllers UNION SELECT signature FROM transitions "
                "UNION SELECT signature FROM models ORDER BY 1"
            ).fetchall()
        return [str(r[0]) for r in rows]

    def snapshot(self, signatures: Iterable[str] | None = None) -> LibrarySnapshot:
        """Every valid row under ``signatures`` (all when None); bad rows skipped and counted."""
        wanted = self.signatures() if signatures is None else list(signatures)
        out: dict[str, SignatureSnapshot] = {}
        for sig in wanted:
            with self._lock:
                models = {
                    str(name): bytes(blob)
                    for name, blob in self._conn.execute(
                        "SELECT name, blob FROM models WHERE signature = ? ORDER BY name", (sig,)
                    )
                }
            out[sig] = SignatureSnapshot(
                tuple(self.load_controllers(sig)),
                tuple(Transition(a, b, n) for (a, b), n in self.load_transitions(sig).items()),
                models,
            )
        return LibrarySnapshot(out)

    def save_snapshot(self, snapshot: LibrarySnapshot) -> None:
        """Save this vehicle's own library: :meth:`save_controllers`, :meth:`save_transitions`
        and :meth:`save_model` for every signature of ``snapshot`` (any thread). What is
        given as what builds it (models, fleet texts: the store process's work) is built
        first, before any transaction: none holds the write lock while a model zips."""
        models = {sig: {name: blob_bytes(blob) for name, blob in part.models.items()}
                  for sig, part in snapshot.signatures.items()}  # fmt: skip
        fleet = {k: text_of(v) for k, v in snapshot.fleet.items()}
        for sig, part in snapshot.signatures.items():
            self.save_controllers(sig, part.controllers)
            self.save_transitions(sig, {(t.from_set, t.to_set): t.count for t in part.transitions})
            for name, blob in models[sig].items():
                self.save_model(name, sig, blob)
        if fleet:  # after the controllers: it never names one the file lacks
            self.save_fleet_state(fleet)

    def save_fleet_state(self, texts: Mapping[str, str | DeferredText]) -> None:
        """Replace the fleet's state (:attr:`LibrarySnapshot.fleet`) in one transaction: a
        kill leaves the old one or the new one whole. A text given as what builds it is
        built first, outside the transaction."""
        texts = {k: text_of(v) for k, v in texts.items()}
        with self._lock, self._conn:
            self._conn.execute("DELETE FROM meta WHERE substr(key, 1, ?) = ?",
                               (len(_FLEET_KEY), _FLEET_KEY))  # fmt: skip
            self._conn.executemany("INSERT INTO meta VALUES (?, ?)",
                                   [(_FLEET_KEY + k, v) for k, v in texts.items()])  # fmt: skip

    def fleet_state(self) -> dict[str, str]:
        """The fleet's state as :meth:`save_fleet_state` wrote it ({} if none)."""
        return self._meta_under(_FLEET_KEY)

    def _meta_under(self, prefix: str) -> dict[str, str]:
        """The meta rows whose key starts with ``prefix``, keyed by the rest."""
        with self._lock:
            rows = self._conn.execute(
                "SELECT key, value FROM meta WHERE substr(key, 1, ?) = ?", (len(prefix), prefix)
            ).fetchall()
        return {str(k)[len(prefix) :]: str(v) for k, v in rows}

    def write_snapshot(
        self, snapshot: LibrarySnapshot, *, origin: str, models: bool = False
    ) -> dict[str, int]:
        """Merge ``snapshot`` into this file in ONE transaction; returns rows new to it.

        New controllers are tagged ``origin``; ones already here keep theirs and take the
        larger importance and use count; transition counts take the larger of the two (so
        writing the same snapshot twice changes nothing). Models are written only when
        ``models`` is set: a learned model describes one airframe, an active set any vehicle
        with the same problem.
        """
        now = time.time()
        new = {"controllers": 0, "transitions": 0, "models": 0}
        built = {sig: {name: blob_bytes(blob) for name, blob in part.models.items()}
                 for sig, part in snapshot.signatures.items()} if models else {}  # fmt: skip
        with self._lock, self._conn:
            for sig, part in snapshot.signatures.items():
                for c in part.controllers:
                    key = encode_active_set(c.active_set)
                    existed = self._conn.execute(
                        "SELECT 1 FROM controllers WHERE signature = ? AND active_set = ?",
                        (sig, key),
                    ).fetchone()
                    new["controllers"] += existed is None
                    self._conn.execute(
                        "INSERT INTO controllers VALUES (?, ?, ?, ?, ?, ?) "
                        "ON CONFLICT (signature, active_set) DO UPDATE SET "
                        "importance = max(importance, excluded.importance), "
                        "uses = max(uses, excluded.uses)",
                        (sig, key, float(c.importance), int(c.uses), origin, now),
                    )
                for t in part.transitions:
                    a, b = encode_active_set(t.from_set), encode_active_set(t.to_set)
                    existed = self._conn.execute(
                        "SELECT 1 FROM transitions WHERE signature = ? AND from_set = ? "
                        "AND to_set = ?",
                        (sig, a, b),
                    ).fetchone()
                    new["transitions"] += existed is None
                    self._conn.execute(
                        "INSERT INTO transitions VALUES (?, ?, ?, ?) "
                        "ON CONFLICT (signature, from_set, to_set) DO UPDATE SET "
                        "count = max(count, excluded.count)",
                        (sig, a, b, int(t.count)),
                    )
                for name, blob in built.get(sig, {}).items():  # built before the transaction
                    new["models"] += 1
                    self._conn.execute(_UPSERT_MODEL, (name, sig, sqlite3.Binary(blob), now))
        return new

    # -- which loop a signature belongs to ----------------------------------------------

    def label_loops(self, loops: Mapping[str, str]) -> None:
        """Record which loop ("position", "attitude") each signature is the problem of: a
        signature is a hash that says nothing by itself, and ``db info`` names the loop."""
        with self._lock, self._conn:
            self._conn.executemany(
                "INSERT INTO meta VALUES (?, ?) ON CONFLICT (key) DO UPDATE SET value = "
                "excluded.value",
                [(f"{_LOOP_KEY}{sig}", name) for sig, name in loops.items()],
            )

    def loop_labels(self) -> dict[str, str]:
        """signature -> loop name, as :meth:`label_loops` recorded (files written before
        it have none)."""
        return self._meta_under(_LOOP_KEY)

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


def _connect(
    path: Path, *, readonly: bool = False, immutable: bool = False
) -> sqlite3.Connection:
    if readonly:
        uri = path.resolve().as_uri() + "?mode=ro" + ("&immutable=1" if immutable else "")
        conn = sqlite3.connect(uri, uri=True, check_same_thread=False, isolation_level=None)
    else:
        conn = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
    try:
        conn.execute("PRAGMA busy_timeout = 2000")
        if not readonly:
            conn.execute("PRAGMA journal_mode = WAL")
            conn.execute("PRAGMA synchronous = NORMAL")
        check = conn.execute("PRAGMA quick_check").fetchone()
        if check is None or check[0] != "ok":
            raise StoreError(f"quick_check failed: {check}")
        tables = _tables(conn)
        refused, cut_short = _not_ours(conn, tables, readonly=readonly)
        if refused is not None:
            raise StoreRefusedError(refused)
        if readonly and not tables:
            raise StoreError("not an epc-offboard library (an empty SQLite file)")
        if cut_short:
            log.warning(
                "library %s: its creation was cut short (empty tables, no schema version): %s",
                path, "read as empty" if readonly else "finished",
            )  # fmt: skip
        if not readonly:
            # the schema and its version in ONE transaction: a kill leaves both or neither
            conn.executescript(f"BEGIN IMMEDIATE;{_SCHEMA}{_SET_VERSION}COMMIT;")
        # Python's sqlite3 with isolation_level=None is in autocommit; `with conn:` below
        # still wraps each batch in one transaction.
        conn.isolation_level = "DEFERRED"
    except Exception:
        conn.close()
        raise
    return conn


def _creation_cut_short(conn: sqlite3.Connection, tables: set[str], *, readonly: bool) -> bool:
    """Whether an unversioned file is only a library whose creation was killed: nothing but
    our tables, all empty (before the schema and its version shared one transaction, a
    kill between the two left that). Such a file is finished, not moved aside; one that
    holds rows is not ours to guess about. Read-only, it reads as empty only when every
    table is there."""
    if not tables <= _TABLES or (readonly and tables != _TABLES):
        return False
    # (names from _TABLES only: nothing from the file reaches the SQL text)
    return all(
        conn.execute(f"SELECT 1 FROM {name} LIMIT 1").fetchone() is None for name in sorted(tables)
    )
