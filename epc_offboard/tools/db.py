"""`epc-offboard db info | export | import | merge`: move experience between vehicles offline.

    db info   LIBRARY                         what a library file holds, per signature
    db export LIBRARY OUT.json                the library as a portable, versioned JSON file
    db import LIBRARY IN.json --config F      add an exported library to LIBRARY
    db merge  LIBRARY OTHER.sqlite [...] --config F    add other vehicles' library files

``--signature SIG`` (repeatable) limits any of them to some problem signatures. Import and
merge need ``--config SERVICE.toml``: they take only the signatures of that service's
problems, and every controller is first validated against its problem (active-set rows in
range, at most N nu rows, linearly independent) — exactly what the service checks when it
loads a library. Without the problem an active set's row indices cannot be checked (a
signature is a hash, and a library file does not hold its problem), so import and merge
refuse to run without ``--config`` rather than write what they cannot check. Learned
models (LWPR) describe one airframe, so import and merge bring them only with ``--models``.

Everything or nothing: everything read is validated before anything is written, and the
write is one transaction. One invalid controller (or a file that does not parse) fails the
command with exit 2, naming the file, signature and controller, and nothing is written;
``--skip-invalid`` instead leaves the invalid controllers out, reports each, and writes the
rest. Source files are opened read-only, never moved or repaired, and nothing (no
``-wal``/``-shm``) is left beside them.
"""

from __future__ import annotations

import argparse
import base64
import binascii
import json
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from epc_offboard.common.errors import EXIT_OK, EpcError, UsageError
from epc_offboard.control.library_types import (
    ActiveSet,
    EntryError,
    LibraryEntry,
    LibrarySnapshot,
    SignatureSnapshot,
    Transition,
    blob_bytes,
    parse_active_set,
    parse_entry,
)
from epc_offboard.store.database import LibraryStore, StoreError

if TYPE_CHECKING:
    from epc_offboard.control.cascade import Cascade
    from epc_offboard.control.qp import MpcProblem

_T = TypeVar("_T")

EXPORT_FORMAT = "epc-offboard-library"
EXPORT_VERSION = 1
# sanity limits on what an export file may hold: far above any real library, low enough
# that a hostile file cannot make the tool allocate without bound
MAX_SIGNATURES = 64
MAX_CONTROLLERS = 100_000  # per signature
MAX_ACTIVE_ROWS = 4_096  # per active set
MAX_MODEL_BYTES = 64 * 1024 * 1024
MAX_SIGNATURE_CHARS = 128


class LibraryFileError(EpcError, ValueError):
    """An export file that does not parse; the message names the file and the field."""


# -- the export file ----------------------------------------------------------------------


def snapshot_to_json(snapshot: LibrarySnapshot, source: str) -> dict[str, Any]:
    return {
        "format": EXPORT_FORMAT,
        "version": EXPORT_VERSION,
        "exported_unix_s": time.time(),
        "source": source,
        "signatures": {
            sig: {
                "controllers": [
                    {
                        "active_set": list(c.active_set),
                        "importance": c.importance,
                        "uses": c.uses,
                        "origin": c.origin,
                    }
                    for c in part.controllers
                ],
                "transitions": [
                    {"from": list(t.from_set), "to": list(t.to_set), "count": t.count}
                    for t in part.transitions
                ],
                "models": {n: base64.b64encode(blob_bytes(b)).decode("ascii")
                           for n, b in part.models.items()},
            }
            for sig, part in snapshot.signatures.items()
        },
    }


def snapshot_from_json(data: Any, source: str) -> LibrarySnapshot:
    """Parse an export file's JSON value; :class:`LibraryFileError` names what is wrong."""

    def fail(where: str, what: str) -> LibraryFileError:
        return LibraryFileError(f"{source}: {where}: {what}")

    if not isinstance(data, dict):
        raise fail("top level", f"must be an object, got {type(data).__name__}")
    if data.get("format") != EXPORT_FORMAT:
        raise fail("format", f"expected {EXPORT_FORMAT!r}, got {data.get('format')!r}")
    if data.get("version") != EXPORT_VERSION:
        raise fail("version", f"expected {EXPORT_VERSION}, got {data.get('version')!r}")
    sigs = data.get("signatures")
    if not isinstance(sigs, dict):
        raise fail("signatures", "must be an object")
    if len(sigs) > MAX_SIGNATURES:
        raise fail("signatures", f"{len(sigs)} exceed the limit {MAX_SIGNATURES}")
    out: dict[str, SignatureSnapshot] = {}
    for sig, part in sigs.items():
        where = f"signatures.{sig[:40]}"
        if not (0 < len(sig) <= MAX_SIGNATURE_CHARS and sig.isprintable()):
            raise fail(where, f"a signature must be 1..{MAX_SIGNATURE_CHARS} printable chars")
        if not isinstance(part, dict) or set(part) - {"controllers", "transitions", "models"}:
            raise fail(where, "must be an object with controllers, transitions, models")
        controllers = _list(part.get("controllers", []), f"{where}.controllers", fail)
        if len(controllers) > MAX_CONTROLLERS:
            raise fail(f"{where}.controllers", f"{len(controllers)} exceed {MAX_CONTROLLERS}")
        parsed_c = []
        for i, c in enumerate(controllers):
            w = f"{where}.controllers[{i}]"
            if not isinstance(c, dict) or set(c) - {"active_set", "importance", "uses", "origin"}:
                raise fail(w, "must be an object with active_set, importance, uses, origin")
            try:
                parsed_c.append(
                    parse_entry(
                        c.get("active_set"),
                        c.get("importance", 0.0),
                        c.get("uses", 0),
                        str(c.get("origin", "solved"))[:64],
                        max_rows=MAX_ACTIVE_ROWS,
                    )
                )
            except EntryError as exc:
                raise fail(w, str(exc)) from exc
        parsed_t = []
        for i, t in enumerate(_list(part.get("transitions", []), f"{where}.transitions", fail)):
            w = f"{where}.transitions[{i}]"
            if not isinstance(t, dict) or set(t) != {"from", "to", "count"}:
                raise fail(w, "must be an object with exactly from, to, count")
            if not _is_int(t["count"]) or t["count"] < 1:
                raise fail(f"{w}.count", f"must be an integer >= 1, got {t['count']!r}")
            parsed_t.append(
                Transition(
                    _active_set(t["from"], f"{w}.from", fail),
                    _active_set(t["to"], f"{w}.to", fail),
                    int(t["count"]),
                )
            )
        models = part.get("models", {})
        if not isinstance(models, dict):
            raise fail(f"{where}.models", "must be an object of name -> base64")
        parsed_m = {}
        for name, text in models.items():
            w = f"{where}.models.{name[:40]}"
            if not isinstance(text, str) or len(text) > MAX_MODEL_BYTES * 4 // 3 + 4:
                raise fail(w, "must be a base64 string within the size limit")
            try:
                parsed_m[name] = base64.b64decode(text, validate=True)
            except binascii.Error as exc:
                raise fail(w, f"not valid base64: {exc}") from exc
        out[sig] = SignatureSnapshot(tuple(parsed_c), tuple(parsed_t), parsed_m)
    return LibrarySnapshot(out)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _list(v: Any, where: str, fail: Any) -> list[Any]:
    if not isinstance(v, list):
        raise fail(where, f"must be a list, got {type(v).__name__}")
    return v


def _active_set(v: Any, where: str, fail: Any) -> ActiveSet:
    try:
        return parse_active_set(v, max_rows=MAX_ACTIVE_ROWS)
    except EntryError as exc:
        raise fail(where, str(exc)) from exc


def read_export_file(path: Path) -> LibrarySnapshot:
    if not path.is_file():
        raise UsageError(f"{path}: no such export file")
    if path.stat().st_size > MAX_SIGNATURES * MAX_MODEL_BYTES:
        raise UsageError(f"{path}: too large to be an exported library")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UsageError(f"{path}: not a JSON library export: {exc}") from exc
    try:
        return snapshot_from_json(data, str(path))
    except LibraryFileError as exc:
        raise UsageError(str(exc)) from exc


# -- selecting and validating -------------------------------------------------------------


def select(snapshot: LibrarySnapshot, signatures: Iterable[str] | None) -> LibrarySnapshot:
    if signatures is None:
        return snapshot
    wanted = set(signatures)
    return LibrarySnapshot({s: p for s, p in snapshot.signatures.items() if s in wanted})


@dataclass(frozen=True)
class Validated:
    """One source checked against a service's problems."""

    kept: LibrarySnapshot  # the config's signatures, only their valid controllers
    invalid: tuple[str, ...]  # "signature S: controller [rows]: why", one per bad controller
    not_taken: tuple[str, ...]  # signatures that are not the config's problems


def config_problems(config_path: str | Path) -> dict[str, MpcProblem]:
    """signature -> MpcProblem of the service configured by ``config_path``."""
    return _problems(_config_cascade(config_path))


def _problems(cascade: Cascade) -> dict[str, MpcProblem]:
    return {p.signature(): p for p in (cascade.position.problem, cascade.attitude.problem)}


_LOOPS_SHOWN = ("position", "attitude")


def _loop_rank(loops: dict[str, str], sig: str) -> tuple[int, str]:
    """``db info`` lists the position loop's signature, the attitude loop's, then others."""
    loop = loops.get(sig, "")
    return (_LOOPS_SHOWN.index(loop) if loop in _LOOPS_SHOWN else len(_LOOPS_SHOWN), sig)


def _bundled_loops() -> dict[str, str]:
    """signature -> loop of the bundled service configs (config/default.toml, sitl.toml):
    names the loops of a library written before the service labelled them."""
    from epc_offboard.common.bundled import bundled_config, bundled_names
    from epc_offboard.store.experience import loop_names

    out: dict[str, str] = {}
    for name in bundled_names():
        out.update(loop_names(_config_cascade(bundled_config(name))))
    return out


def _config_cascade(config_path: str | Path) -> Cascade:
    from epc_offboard.common.bundled import bundled_config
    from epc_offboard.common.configio import ConfigError
    from epc_offboard.control.cascade import Cascade
    from epc_offboard.service.config import load_service_config

    try:  # a path, or a bundled config by name (`--config sitl`), as `run --config`
        cfg = load_service_config(bundled_config(str(config_path)))
    except ConfigError as exc:
        raise UsageError(str(exc)) from exc
    return Cascade(cfg.position, cfg.attitude, cfg.estimator, 1.0 / cfg.loops.position_rate_hz,
                   airframe=cfg.vehicle)  # fmt: skip


def validate_against_problems(
    snapshot: LibrarySnapshot, problems: dict[str, MpcProblem], config_path: str
) -> Validated:
    """Check every controller of the problems' signatures as the service does on load.
    Transitions are kept only between valid controllers of the same source."""
    from epc_offboard.control.epc import ExperienceController

    invalid: list[str] = []
    not_taken: list[str] = []
    kept: dict[str, SignatureSnapshot] = {}
    for sig, part in snapshot.signatures.items():
        problem = problems.get(sig)
        if problem is None:
            not_taken.append(f"signature {sig}: not a problem of {config_path}")
            continue
        checker = ExperienceController(problem, max_size=1)
        ok: list[LibraryEntry] = []
        for c in part.controllers:
            try:
                checker.import_entries([c])
            except ValueError as exc:
                invalid.append(f"signature {sig}: controller {list(c.active_set)}: {exc}")
                continue
            ok.append(c)
        sets = {c.active_set for c in ok}
        transitions = tuple(
            t for t in part.transitions if t.from_set in sets and t.to_set in sets
        )
        kept[sig] = SignatureSnapshot(tuple(ok), transitions, part.models)
    return Validated(LibrarySnapshot(kept), tuple(invalid), tuple(not_taken))


# -- the command --------------------------------------------------------------------------


def add_db_arguments(db: argparse.ArgumentParser) -> None:
    db.add_argument("action", choices=["info", "export", "import", "merge"])
    db.add_argument("paths", nargs="*", metavar="PATH", help="LIBRARY, then the other file(s)")
    db.add_argument(
        "--signature", action="append", default=None, metavar="SIG",
        help="only this problem signature (repeatable)",
    )  # fmt: skip
    db.add_argument(
        "--config", default=None, metavar="FILE",
        help="import/merge (required): only this service config's problems, each controller "
        "validated against its problem",
    )  # fmt: skip
    db.add_argument(
        "--skip-invalid", action="store_true",
        help="import/merge: leave invalid controllers out (each reported) and write the rest; "
        "by default one invalid controller fails the command and nothing is written",
    )  # fmt: skip
    db.add_argument(
        "--models", action="store_true", help="import/merge: also the learned models (LWPR)"
    )


_MAX_LISTED = 20  # invalid controllers listed per source; the rest are counted

_USAGE = {
    "info": "epc-offboard db info LIBRARY.sqlite",
    "export": "epc-offboard db export LIBRARY.sqlite OUT.json",
    "import": "epc-offboard db import LIBRARY.sqlite IN.json --config SERVICE.toml",
    "merge": "epc-offboard db merge LIBRARY.sqlite OTHER.sqlite [...] --config SERVICE.toml",
}


def run_db_command(args: argparse.Namespace) -> int:
    n = len(args.paths)
    if (args.action in ("info",) and n != 1) or (args.action in ("export", "import") and n != 2):
        raise UsageError(f"usage: {_USAGE[args.action]}")
    if args.action == "merge" and n < 2:
        raise UsageError(f"usage: {_USAGE['merge']}")
    if args.action in ("info", "export") and (args.config or args.models or args.skip_invalid):
        raise UsageError(
            f"--config, --models and --skip-invalid apply to import and merge, not {args.action}"
        )
    if args.action in ("import", "merge") and not args.config:
        raise UsageError(
            f"db {args.action} needs --config SERVICE.toml: every controller is checked "
            "against that service's problems (active-set rows in range, at most N nu rows, "
            "linearly independent) before anything is written, and a library or export file "
            "does not hold its problems, so without --config nothing can be checked"
        )
    library = Path(args.paths[0])
    try:
        if args.action == "info":
            return _info(library, args.signature)
        if args.action == "export":
            return _export(library, Path(args.paths[1]), args.signature)
        if args.action == "import":
            sources = [(args.paths[1], read_export_file(Path(args.paths[1])))]
        else:
            sources = [(p, read_library(Path(p))[0]) for p in args.paths[1:]]
        return _write(library, sources, args)
    except StoreError as exc:
        raise UsageError(str(exc)) from exc


def read_library(path: Path) -> tuple[LibrarySnapshot, int]:
    """The whole library file and its count of unreadable rows (:func:`_read_store`)."""
    return _read_store(path, lambda store: (store.snapshot(), store.skipped_rows))


def _read_store(path: Path, read: Callable[[LibraryStore], _T]) -> _T:
    """``read`` of the library file, leaving nothing beside it.

    A WAL-mode file opened read-only the ordinary way gets ``-wal`` and ``-shm`` files that
    a read-only connection cannot remove. With no ``-wal`` beside it no process has the file
    open and all of it is in the main file, so it is read as immutable (nothing created);
    if a ``-wal`` appeared or the file changed meanwhile (a service started writing), it is
    read again through the writer's WAL, whose files are then the writer's.
    """
    wal = Path(f"{path}-wal")
    if not wal.exists() and path.is_file():
        before = _file_identity(path)
        with LibraryStore.open_readonly(path, immutable=True) as store:
            result = read(store)
        if not wal.exists() and _file_identity(path) == before:
            return result
    with LibraryStore.open_readonly(path) as store:
        return read(store)


def _file_identity(path: Path) -> tuple[int, int, int]:
    st = path.stat()
    return st.st_ino, st.st_size, st.st_mtime_ns


def _info(path: Path, signatures: list[str] | None) -> int:
    whole, skipped = read_library(path)
    snap = select(whole, signatures)
    loops = _read_store(path, lambda store: store.loop_labels())
    if set(snap.signatures) - set(loops):  # a file from before the labels, or a merge
        loops = {**_bundled_loops(), **loops}
    print(f"{path}: {len(snap.signatures)} problem signature(s)")
    for sig, part in sorted(snap.signatures.items(), key=lambda kv: _loop_rank(loops, kv[0])):
        loop = f"{loops.get(sig, 'unknown')} loop"
        origins: dict[str, int] = {}
        for c in part.controllers:
            kind = c.origin.split(":", 1)[0]
            origins[kind] = origins.get(kind, 0) + 1
        by_origin = ", ".join(f"{k} {v}" for k, v in sorted(origins.items())) or "none"
        print(
            f"  {loop:<13}  {sig}: {len(part.controllers)} controllers ({by_origin}), "
            f"{len(part.transitions)} transitions, {len(part.models)} models"
            + (f" [{', '.join(sorted(part.models))}]" if part.models else "")
        )
    if set(snap.signatures) - set(loops):
        print("  (unknown loop: a problem of no bundled config, in a file the service did not "
              "write; the service records each signature's loop in the files it writes)")
    if skipped:
        print(f"  {skipped} unreadable row(s) skipped")
    return EXIT_OK


def _export(path: Path, out: Path, signatures: list[str] | None) -> int:
    if str(out) != "-":  # said before the library is read (a traceback, and OUT.tmp left)
        if out.is_dir():
            raise UsageError(f"{out}: is a directory: give the export a file name, e.g. "
                             f"{out / (path.stem + '.json')}")  # fmt: skip
        if not out.parent.is_dir():
            raise UsageError(f"{out}: no folder {out.parent}")
    snap = select(read_library(path)[0], signatures)
    text = json.dumps(snapshot_to_json(snap, path.name), indent=1)
    if str(out) == "-":
        sys.stdout.write(text + "\n")
    else:
        tmp = out.with_name(out.name + ".tmp")
        try:
            tmp.write_text(text + "\n", encoding="utf-8")
            tmp.replace(out)  # never leave a half-written export behind
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise UsageError(f"{out}: cannot write the export: {exc.strerror or exc}") from exc
        counts = snap.counts()
        print(
            f"{out}: {counts['controllers']} controllers, {counts['transitions']} transitions, "
            f"{counts['models']} models under {counts['signatures']} signature(s)"
        )
    return EXIT_OK


def _write(
    library: Path, sources: list[tuple[str, LibrarySnapshot]], args: argparse.Namespace
) -> int:
    from epc_offboard.store.experience import loop_names

    cascade = _config_cascade(args.config)
    problems = _problems(cascade)
    prepared = []
    invalid = 0
    for name, snap in sources:  # validate everything before touching the library
        checked = validate_against_problems(select(snap, args.signature), problems, args.config)
        for reason in checked.not_taken:
            print(f"{name}: not taken: {reason}", file=sys.stderr)
        verb = "left out" if args.skip_invalid else "invalid"
        for reason in checked.invalid[:_MAX_LISTED]:
            print(f"{name}: {verb}: {reason}", file=sys.stderr)
        if len(checked.invalid) > _MAX_LISTED:
            print(f"{name}: ... and {len(checked.invalid) - _MAX_LISTED} more", file=sys.stderr)
        invalid += len(checked.invalid)
        prepared.append((name, checked.kept))
    if invalid and not args.skip_invalid:
        raise UsageError(
            f"{invalid} invalid controller(s) (listed above): nothing written to {library}; "
            "--skip-invalid writes the rest and leaves these out"
        )
    with LibraryStore.open(library, repair=False) as store:
        store.label_loops(loop_names(cascade))  # for `db info`
        for name, snap in prepared:
            new = store.write_snapshot(
                snap, origin=f"{args.action}:{Path(name).name}"[:64], models=args.models
            )
            print(
                f"{library}: from {name}: {new['controllers']} new controllers, "
                f"{new['transitions']} new transitions"
                + (f", {new['models']} models" if args.models else "")
            )
    if invalid:
        print(f"{library}: {invalid} invalid controller(s) left out (--skip-invalid)")
    return EXIT_OK
