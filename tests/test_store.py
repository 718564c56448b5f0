"""The SQLite library store: round trips, bad rows, corrupt files, kill -9 durability."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap

import pytest

from epc_offboard.store import (
    LibraryStore,
    StoredController,
    decode_active_set,
    encode_active_set,
)

SIG = "sig-a"


def test_controllers_round_trip_and_merge_keeps_most_important(tmp_path):
    path = tmp_path / "lib.sqlite"
    with LibraryStore.open(path) as store:
        store.save_controllers(
            SIG, [StoredController((1, 5, 9), 2.0, 3), StoredController((), 1.0, 1)]
        )
        store.save_controllers(SIG, [StoredController((1, 5, 9), 1.5, 7, "shared:2")])
        store.save_controllers("sig-b", [StoredController((4,), 9.0, 1)])
    with LibraryStore.open(path) as store:
        got = store.load_controllers(SIG)
        assert got == [StoredController((1, 5, 9), 2.0, 7, "solved"), StoredController((), 1.0, 1)]
        assert store.summary()[SIG]["controllers"] == 2
        assert store.summary()["sig-b"]["controllers"] == 1


def test_transitions_and_models_round_trip(tmp_path):
    with LibraryStore.open(tmp_path / "lib.sqlite") as store:
        store.save_transitions(SIG, {((1,), (2, 3)): 4, ((), (1,)): 1})
        store.save_model("lwpr.position", SIG, b"\x00\x01blob")
        assert store.load_transitions(SIG) == {((1,), (2, 3)): 4, ((), (1,)): 1}
        assert store.load_model("lwpr.position", SIG) == b"\x00\x01blob"
        assert store.load_model("lwpr.position", "other") is None


@pytest.mark.parametrize("text", ["[3,1]", "[1,1]", "[-1]", "{}", "[1.5]", "[true]", "nope"])
def test_bad_active_set_text_is_rejected(text):
    with pytest.raises(ValueError):  # noqa: PT011 - json errors are ValueErrors too
        decode_active_set(text)


def test_encode_sorts():
    assert encode_active_set([5, 1]) == "[1,5]"


def test_bad_rows_are_skipped_not_fatal(tmp_path):
    path = tmp_path / "lib.sqlite"
    with LibraryStore.open(path) as store:
        store.save_controllers(SIG, [StoredController((2,), 1.0, 1)])
    conn = sqlite3.connect(path)
    conn.execute("INSERT INTO controllers VALUES (?, '[9, 3]', 5.0, 1, 'solved', 0)", (SIG,))
    conn.commit()
    conn.close()
    with LibraryStore.open(path) as store:
        assert store.load_controllers(SIG) == [StoredController((2,), 1.0, 1)]
        assert store.skipped_rows == 1


@pytest.mark.parametrize(
    "damage",
    [
        lambda p: p.write_bytes(b"this is not a database at all" * 100),
        lambda p: p.write_bytes(p.read_bytes()[:1500]),  # truncated
        lambda p: _set_version(p, "999"),
    ],
    ids=["garbage", "truncated", "other-schema"],
)
def test_unusable_file_is_moved_aside_and_store_starts_empty(tmp_path, damage, caplog):
    path = tmp_path / "lib.sqlite"
    with LibraryStore.open(path) as store:
        store.save_controllers(SIG, [StoredController((i,), 1.0, 1) for i in range(200)])
    damage(path)
    with LibraryStore.open(path) as store:
        assert store.load_controllers(SIG) == []
    aside = list(tmp_path.glob("lib.sqlite.corrupt-*"))
    assert [p.name for p in aside if not p.name.endswith(("-wal", "-shm"))]
    assert "moved aside" in caplog.text


def _set_version(path, version):
    conn = sqlite3.connect(path)
    conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (version,))
    conn.commit()
    conn.close()


def test_kill_9_keeps_every_committed_controller(tmp_path):
    """A writer process is killed with SIGKILL mid-stream; all it reported committed survives."""
    path = tmp_path / "lib.sqlite"
    script = textwrap.dedent(
        f"""
        import sys
        from epc_offboard.store import LibraryStore, StoredController
        store = LibraryStore.open({str(path)!r})
        i = 0
        while True:
            store.save_controllers("sig", [StoredController((i, i + 1), float(i), 1)])
            print(i, flush=True)
            i += 1
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    committed = -1
    for line in proc.stdout:
        committed = int(line)
        if committed >= 300:
            break
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with LibraryStore.open(path) as store:
        got = {c.active_set for c in store.load_controllers("sig")}
    assert {(i, i + 1) for i in range(committed + 1)} <= got
    assert not list(tmp_path.glob("*.corrupt-*"))


def test_db_info_command(tmp_path, capsys):
    from epc_offboard.cli import main

    path = tmp_path / "lib.sqlite"
    with LibraryStore.open(path) as store:
        store.save_controllers(
            SIG, [StoredController((1,), 1.0, 1), StoredController((2,), 1.0, 1)]
        )
    assert main(["db", "info", str(path)]) == 0
    assert f"{SIG}: 2 controllers" in capsys.readouterr().out
    assert main(["db", "info", str(tmp_path / "missing.sqlite")]) == 2
    assert "no such library" in capsys.readouterr().err
