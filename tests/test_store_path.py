"""A `store.path` the service cannot use is refused with exit code 2, naming the key, the path
and why, and nothing there is moved or written (stop 41): a directory was renamed
``.corrupt-...`` as if it were a damaged file, another application's SQLite file and a newer
release's library were moved aside, and a parent that is a file said neither the key nor
the path. Only a file that is not a database (corruption) is still moved aside. Real
processes, real files: `epc-offboard run`, `sim`, `db`.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from epc_offboard.cli import main
from epc_offboard.common import jit
from epc_offboard.common.ports import free_port
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.store.database import (
    LibraryStore,
    StoreRefusedError,
    library_refusal,
)

ROOT = Path(__file__).resolve().parent.parent
SIG = "sig"


def _directory(p: Path) -> None:
    p.mkdir()
    (p / "keep.txt").write_text("the user's\n")


def _parent_is_a_file(p: Path) -> None:
    p.parent.parent.mkdir(exist_ok=True)
    p.parent.write_text("a file, not a folder\n")


def _dangling_symlink(p: Path) -> None:
    p.symlink_to(p.parent / "mounted-later" / "lib.sqlite")


def _foreign_sqlite(p: Path) -> None:
    with sqlite3.connect(p) as db:  # another application's file (a browser's history)
        db.execute("CREATE TABLE moz_places (url TEXT)")
        db.execute("INSERT INTO moz_places VALUES ('https://px4.io')")
    db.close()


def _other_version(p: Path) -> None:
    with LibraryStore.open(p) as store:  # a newer release's library: not ours to destroy
        store.save_controllers(SIG, [LibraryEntry((1, 2), 1.0, 1)])
    with sqlite3.connect(p) as db:
        db.execute("UPDATE meta SET value = '999' WHERE key = 'schema_version'")
    db.close()


# (make the thing at the path, the path's name, what the message says)
CASES: dict[str, tuple[Callable[[Path], None], str, str]] = {
    "directory": (_directory, "lib.sqlite", "is a directory"),
    "parent-is-a-file": (_parent_is_a_file, "state/lib.sqlite", "is not a directory"),
    "dangling-symlink": (_dangling_symlink, "lib.sqlite", "which does not exist"),
    "foreign-sqlite": (_foreign_sqlite, "lib.sqlite", "its tables: moz_places"),
    "other-version": (_other_version, "lib.sqlite", "schema version 999"),
}


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder``: a file's bytes, None for a directory or a symlink."""
    out: dict[str, bytes | None] = {}
    for p in sorted(folder.rglob("*")):
        out[str(p.relative_to(folder))] = (
            None if p.is_symlink() or p.is_dir() else p.read_bytes()
        )
    return out


def _service_config(folder: Path, store_path: str) -> Path:
    config = (ROOT / "config" / "sitl.toml").read_text()
    config = config.replace("udpin://127.0.0.1:14540", f"udpin://127.0.0.1:{free_port()}")
    config = config.replace("out/sitl-service/library.sqlite", store_path)
    path = folder / "service.toml"
    path.write_text(config)
    return path


def _run(config: Path, *, user: list[str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*(user or []), sys.executable, "-m", "epc_offboard", "run", "--config", str(config)],
        capture_output=True, text=True, timeout=180, cwd=config.parent,
    )  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_service_refuses_a_store_path_it_cannot_use_and_moves_nothing(
    tmp_path: Path, case: str
) -> None:
    make, name, reason = CASES[case]
    folder = tmp_path / "data"
    folder.mkdir()
    lib = folder / name
    make(lib)
    before = _snapshot(folder)
    config = _service_config(tmp_path, str(lib))
    proc = _run(config)
    assert proc.returncode == 2, proc.stderr
    for part in (str(config), "`store.path`", str(lib), reason, "nothing was moved"):
        assert part in proc.stderr, f"{part!r} not in {proc.stderr}"
    assert "Traceback" not in proc.stderr
    assert _snapshot(folder) == before  # nothing renamed, created or written


def test_a_path_the_filesystem_refuses_is_refused_after_the_open_fails() -> None:
    # /proc takes no new file, though root passes every permission check there: found only
    # when SQLite's open fails, which is not corruption (nothing to move aside)
    with pytest.raises(StoreRefusedError, match="cannot open or write it"):
        LibraryStore.open("/proc/epc-offboard-lib.sqlite")
    with tempfile.TemporaryDirectory() as folder:
        proc = _run(_service_config(Path(folder), "/proc/epc-offboard-lib.sqlite"))
    assert proc.returncode == 2, proc.stderr
    assert "`store.path` /proc/epc-offboard-lib.sqlite: cannot open or write it" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.fixture
def open_folder() -> Iterator[Path]:
    """A folder another user can read (pytest's tmp_path is root's alone)."""
    folder = Path(tempfile.mkdtemp(prefix="store-path-"))
    folder.chmod(0o755)
    try:
        yield folder
    finally:
        shutil.rmtree(folder)


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root to run the service as another user")  # fmt: skip
def test_a_directory_the_services_user_cannot_write_is_refused(open_folder: Path) -> None:
    # the systemd unit runs the service as its own user: a library under root's folder
    # failed in SQLite's open, taken for corruption
    locked = open_folder / "root-only"
    locked.mkdir(mode=0o755)
    config = _service_config(open_folder, str(locked / "lib.sqlite"))
    config.chmod(0o644)
    nobody = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
    proc = _run(config, user=nobody)
    assert proc.returncode == 2, proc.stderr
    says = f"`store.path` {locked / 'lib.sqlite'}: directory {locked} is not writable by this"
    assert f"{says} user (uid 65534)" in proc.stderr
    assert list(locked.iterdir()) == []


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_store_refuses_and_moves_nothing_in_process(tmp_path: Path, case: str) -> None:
    make, name, reason = CASES[case]
    lib = tmp_path / name
    make(lib)
    before = _snapshot(tmp_path)
    assert reason in (library_refusal(lib) or "")
    for repair in (True, False):
        with pytest.raises(StoreRefusedError, match=reason):
            LibraryStore.open(lib, repair=repair)
    assert _snapshot(tmp_path) == before


def test_a_file_that_is_not_a_database_is_still_moved_aside_and_said_corrupt(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    lib = tmp_path / "lib.sqlite"
    lib.write_bytes(b"not a database" * 200)
    assert library_refusal(lib) is None  # not refused: the service repairs it
    with LibraryStore.open(lib) as store:
        assert store.signatures() == []
    [aside] = tmp_path.glob("lib.sqlite.corrupt-*")
    assert aside.read_bytes() == b"not a database" * 200
    assert "is corrupt" in caplog.text
    assert "moved aside" in caplog.text


def _never_fly(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    flown: list[object] = []

    def run_one(o: object) -> int:
        flown.append(o)
        return 0

    monkeypatch.setattr("epc_offboard.tools.sim.command.run_one", run_one)
    monkeypatch.setattr("epc_offboard.tools.sim.command.check_ports", lambda _o: None)
    return flown


@pytest.mark.parametrize("case", ["directory", "foreign-sqlite", "other-version"])
def test_sim_refuses_a_library_in_its_out_folder_before_flying(
    tmp_path: Path, case: str, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    flown = _never_fly(monkeypatch)
    make, _name, reason = CASES[case]
    out = tmp_path / "out"
    out.mkdir()
    lib = out / "library-1.sqlite"
    make(lib)
    before = _snapshot(out)
    assert main(["sim", "--out", str(out), "--gcs-port", "0"]) == 2
    err = capsys.readouterr().err
    for part in (f"--out {out}", "`store.path`", str(lib), reason):
        assert part in err, f"{part!r} not in {err}"
    assert not flown
    assert _snapshot(out) == before


def test_db_names_what_is_wrong_with_the_path(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "lib.sqlite"
    _directory(folder)
    assert main(["db", "info", str(folder)]) == 2
    assert "is a directory" in capsys.readouterr().err  # it said "no such library file"
    foreign = tmp_path / "places.sqlite"
    _foreign_sqlite(foreign)
    good = tmp_path / "good.sqlite"
    LibraryStore.open(good).close()
    before = foreign.read_bytes()
    config = str(ROOT / "config" / "sitl.toml")
    assert main(["db", "merge", "--config", config, str(foreign), str(good)]) == 2
    assert "its tables: moz_places" in capsys.readouterr().err
    assert foreign.read_bytes() == before


def test_sim_says_once_that_a_cold_cache_compiles_and_nothing_when_warm(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # a fresh install's first sim compiled for 1-2 min without a word: taken for a hang
    if not jit.numba_installed():
        pytest.skip("no numba: nothing compiles")
    flown = _never_fly(monkeypatch)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv(jit.ENV, raising=False)
    argv = ["sim", "--out", str(tmp_path / "out"), "--gcs-port", "0"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert err.count("compiling the control kernels") == 1, err
    assert "epc-offboard sim: first run" in err
    assert jit.mark_cache_warm()
    assert main(argv) == 0
    assert "compiling" not in capsys.readouterr().err
    monkeypatch.setenv(jit.ENV, "0")  # the numpy twins: nothing compiles
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cold-again"))
    assert main(argv) == 0
    assert "compiling" not in capsys.readouterr().err
    assert len(flown) == 3


def test_db_export_to_a_directory_says_so_and_leaves_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # it ended in a traceback (IsADirectoryError from the .tmp's rename) and left OUT.tmp
    good = tmp_path / "good.sqlite"
    LibraryStore.open(good).close()
    folder = tmp_path / "exports"
    folder.mkdir()
    assert main(["db", "export", str(good), str(folder)]) == 2
    assert f"{folder}: is a directory" in capsys.readouterr().err
    assert main(["db", "export", str(good), str(tmp_path / "none" / "x.json")]) == 2
    assert "no folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exports", "good.sqlite"]
    assert list(folder.iterdir()) == []
