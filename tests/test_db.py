"""`epc-offboard db info | export | import | merge`: offline transfer of libraries."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from epc_offboard.cli import build_parser, main
from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.service.config import load_service_config
from epc_offboard.store.database import LibraryStore

SITL_CONFIG = "config/sitl.toml"
# import and merge check every controller against the problems of a service config: the
# libraries here hold the SITL service's position (SIG) and attitude (OTHER) problems
_CFG = load_service_config(SITL_CONFIG)
_CASCADE = Cascade(_CFG.position, _CFG.attitude, _CFG.estimator, 1.0 / _CFG.loops.position_rate_hz)
POS_PROBLEM = _CASCADE.position.problem
SIG, OTHER = POS_PROBLEM.signature(), _CASCADE.attitude.problem.signature()
CFG = ["--config", SITL_CONFIG]


def _library(path, controllers, transitions=None, model=None, sig=SIG):
    with LibraryStore.open(path) as store:
        store.save_controllers(sig, controllers)
        if transitions:
            store.save_transitions(sig, transitions)
        if model is not None:
            store.save_model("estimator.lwpr", sig, model)
    return path


def _contents(path):
    with LibraryStore.open_readonly(path) as store:
        return store.snapshot()


def test_export_import_round_trip_models_only_on_request(tmp_path, capsys):
    src = _library(
        tmp_path / "v1.sqlite",
        [LibraryEntry((1, 4), 5.0, 9), LibraryEntry((), 2.0, 3)],
        {((), (1, 4)): 6},
        model=b"\x00lwpr\xff",
    )
    out = tmp_path / "v1.json"
    assert main(["db", "export", str(src), str(out)]) == 0
    exported = json.loads(out.read_text())
    assert exported["format"] == "epc-offboard-library"
    assert exported["signatures"][SIG]["transitions"] == [{"from": [], "to": [1, 4], "count": 6}]

    dst = tmp_path / "v2.sqlite"
    assert main(["db", "import", str(dst), str(out), *CFG]) == 0
    got = _contents(dst).signatures[SIG]
    assert {(c.active_set, c.importance, c.uses) for c in got.controllers} == {
        ((1, 4), 5.0, 9),
        ((), 2.0, 3),
    }
    assert all(c.origin == "import:v1.json" for c in got.controllers)
    assert [(t.from_set, t.to_set, t.count) for t in got.transitions] == [((), (1, 4), 6)]
    assert dict(got.models) == {}  # a model is one airframe's: only with --models

    assert main(["db", "import", str(dst), str(out), "--models", *CFG]) == 0
    assert dict(_contents(dst).signatures[SIG].models) == {"estimator.lwpr": b"\x00lwpr\xff"}
    assert "0 new controllers" in capsys.readouterr().out  # second import added nothing


def test_merge_is_a_union_and_idempotent(tmp_path):
    v1 = _library(tmp_path / "v1.sqlite", [LibraryEntry((1,), 3.0, 2)], {((1,), (1,)): 4})
    v2 = _library(
        tmp_path / "v2.sqlite",
        [LibraryEntry((1,), 7.0, 1), LibraryEntry((2, 5), 1.0, 1)],
        {((1,), (1,)): 2},
    )
    v3 = _library(tmp_path / "v3.sqlite", [LibraryEntry((9,), 1.0, 1)], sig=OTHER)
    fleet = tmp_path / "fleet.sqlite"
    for _ in range(2):  # merging the same files again changes nothing
        assert main(["db", "merge", str(fleet), str(v1), str(v2), str(v3), *CFG]) == 0
        snap = _contents(fleet)
        got = {c.active_set: (c.importance, c.uses) for c in snap.signatures[SIG].controllers}
        assert got == {(1,): (7.0, 2), (2, 5): (1.0, 1)}
        assert [t.count for t in snap.signatures[SIG].transitions] == [4]
        assert [c.active_set for c in snap.signatures[OTHER].controllers] == [(9,)]


def test_signature_filter(tmp_path):
    v1 = _library(tmp_path / "v1.sqlite", [LibraryEntry((1,), 1.0, 1)])
    _library(v1, [LibraryEntry((2,), 1.0, 1)], sig=OTHER)
    out = tmp_path / "only.json"
    assert main(["db", "export", str(v1), str(out), "--signature", OTHER]) == 0
    assert list(json.loads(out.read_text())["signatures"]) == [OTHER]


def _valid_export():
    return {
        "format": "epc-offboard-library",
        "version": 1,
        "signatures": {
            SIG: {
                "controllers": [{"active_set": [1, 2], "importance": 1.0, "uses": 1}],
                "transitions": [],
                "models": {},
            }
        },
    }


def _with(path, value):
    def edit(doc):
        node = doc
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
        return doc

    return edit


C0 = ["signatures", SIG, "controllers", 0]


@pytest.mark.parametrize(
    ("edit", "named"),
    [
        (_with(["format"], "something-else"), "format"),
        (_with(["version"], 2), "version"),
        (_with(["signatures"], []), "signatures"),
        (_with([*C0, "active_set"], [2, 1]), "active_set"),
        (_with([*C0, "active_set"], [1, 1]), "active_set"),
        (_with([*C0, "active_set"], [-1]), "active_set"),
        (_with([*C0, "active_set"], [True]), "active_set"),
        (_with([*C0, "active_set"], "1,2"), "active_set"),
        (_with([*C0, "active_set"], list(range(5000))), "active_set"),
        (_with([*C0, "importance"], float("nan")), "importance"),
        (_with([*C0, "uses"], -3), "uses"),
        (_with([*C0, "gain"], [1.0]), "controllers[0]"),
        (_with(["signatures", SIG, "transitions"], [{"from": [1], "to": [2]}]), "transitions[0]"),
        (
            _with(["signatures", SIG, "transitions"], [{"from": [1], "to": [2], "count": 0}]),
            "count",
        ),
        (_with(["signatures", SIG, "models"], {"m": "***"}), "models.m"),
    ],
)
def test_bad_export_is_rejected_naming_the_field_and_changes_nothing(
    tmp_path, capsys, edit, named
):
    lib = _library(tmp_path / "lib.sqlite", [LibraryEntry((3,), 1.0, 1)])
    before = _contents(lib)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(edit(_valid_export())))
    assert main(["db", "import", str(lib), str(bad), *CFG]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err
    assert named in err
    assert _contents(lib) == before


@pytest.mark.parametrize("text", ["", "{not json", '{"format": "epc-offboard-library"'])
def test_export_that_is_not_json_is_rejected(tmp_path, capsys, text):
    lib = _library(tmp_path / "lib.sqlite", [LibraryEntry((3,), 1.0, 1)])
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    assert main(["db", "import", str(lib), str(bad), *CFG]) == 2
    assert "not a JSON library export" in capsys.readouterr().err
    assert [c.active_set for c in _contents(lib).signatures[SIG].controllers] == [(3,)]


def test_corrupt_files_are_reported_and_never_moved(tmp_path, capsys):
    good = _library(tmp_path / "good.sqlite", [LibraryEntry((3,), 1.0, 1)])
    before = _contents(good)
    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(b"this is not a database" * 200)
    assert main(["db", "merge", str(good), str(garbage), *CFG]) == 2
    assert "garbage.sqlite: not a usable library" in capsys.readouterr().err
    assert main(["db", "info", str(garbage)]) == 2
    assert main(["db", "export", str(garbage), str(tmp_path / "x.json")]) == 2
    assert main(["db", "merge", str(garbage), str(good), *CFG]) == 2  # a corrupt destination
    assert garbage.read_bytes() == b"this is not a database" * 200
    assert not list(tmp_path.glob("*.corrupt-*"))
    assert not (tmp_path / "x.json").exists()
    assert _contents(good) == before


def test_usage_errors(tmp_path, capsys):
    lib = _library(tmp_path / "lib.sqlite", [LibraryEntry((3,), 1.0, 1)])
    assert main(["db", "export", str(lib)]) == 2
    assert "usage: epc-offboard db export" in capsys.readouterr().err
    assert main(["db", "merge", str(lib)]) == 2
    assert main(["db", "info", str(lib), "--models"]) == 2
    assert main(["db", "import", str(lib), str(tmp_path / "missing.json"), *CFG]) == 2
    assert "no such export file" in capsys.readouterr().err


def _mixed_source(tmp_path, action):
    """A library (merge) or export (import) of 2 valid controllers, 2 invalid ones and a
    signature that is not the SITL service's; returns (path, the invalid active sets)."""
    # a row out of range; more rows than the problem has inputs
    bad = [(POS_PROBLEM.n_con + 5,), tuple(range(POS_PROBLEM.n_u + 1))]
    src = _library(
        tmp_path / "v1.sqlite",
        [LibraryEntry((), 3.0, 1), LibraryEntry((1,), 2.0, 1)]
        + [LibraryEntry(a, 1.0, 1) for a in bad],
        {((), (1,)): 4, ((), bad[0]): 2},
    )
    _library(src, [LibraryEntry((), 1.0, 1)], sig="f" * 32)  # another vehicle's problem
    if action == "merge":
        return src, bad
    out = tmp_path / "v1.json"
    assert main(["db", "export", str(src), str(out)]) == 0
    return out, bad


@pytest.mark.parametrize("action", ["import", "merge"])
def test_one_invalid_controller_fails_the_command_and_writes_nothing(tmp_path, capsys, action):
    src, bad = _mixed_source(tmp_path, action)
    dst = _library(tmp_path / "v2.sqlite", [LibraryEntry((7,), 1.0, 1)])
    before = _contents(dst)
    capsys.readouterr()
    assert main(["db", action, str(dst), str(src), *CFG]) == 2
    err = capsys.readouterr().err
    for active_set in bad:  # each named with its file and signature
        assert f"{src}: invalid: signature {SIG}: controller {list(active_set)}" in err
    assert "out of range" in err
    assert "2 invalid controller(s)" in err
    assert "nothing written" in err
    assert "--skip-invalid" in err
    assert _contents(dst) == before


@pytest.mark.parametrize("action", ["import", "merge"])
def test_skip_invalid_writes_the_rest_and_reports_what_it_left_out(tmp_path, capsys, action):
    src, bad = _mixed_source(tmp_path, action)
    dst = tmp_path / "v2.sqlite"
    capsys.readouterr()
    assert main(["db", action, str(dst), str(src), *CFG, "--skip-invalid"]) == 0
    captured = capsys.readouterr()
    for active_set in bad:
        assert f"{src}: left out: signature {SIG}: controller {list(active_set)}" in captured.err
    assert f"{src}: not taken: signature {'f' * 32}: not a problem of" in captured.err
    assert "2 invalid controller(s) left out" in captured.out
    snap = _contents(dst)
    assert list(snap.signatures) == [SIG]
    assert {c.active_set for c in snap.signatures[SIG].controllers} == {(), (1,)}
    # the transition to a left-out controller goes with it
    assert [(t.from_set, t.to_set) for t in snap.signatures[SIG].transitions] == [((), (1,))]


@pytest.mark.parametrize("action", ["import", "merge"])
def test_without_config_nothing_is_written_and_the_message_names_config(
    tmp_path, capsys, action
):
    # an out-of-range row cannot be seen without the problem: refused, not written
    src, _ = _mixed_source(tmp_path, action)
    dst = tmp_path / "v2.sqlite"
    capsys.readouterr()
    assert main(["db", action, str(dst), str(src)]) == 2
    assert f"db {action} needs --config SERVICE.toml" in capsys.readouterr().err
    assert not dst.exists()


@pytest.mark.parametrize("action", ["info", "export"])
def test_reading_a_library_leaves_nothing_beside_it(tmp_path, action):
    lib = _library(tmp_path / "lib.sqlite", [LibraryEntry((1,), 1.0, 1)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lib.sqlite"]
    mtime_ns = lib.stat().st_mtime_ns
    args = [str(tmp_path / "out.json")] if action == "export" else []
    assert main(["db", action, str(lib), *args]) == 0
    assert not list(tmp_path.glob("lib.sqlite-*"))  # no -wal, no -shm
    assert lib.stat().st_mtime_ns == mtime_ns


def test_a_library_open_by_a_writer_is_read_through_its_wal(tmp_path, capsys):
    # a running service holds the file open; what it committed is still only in its WAL
    lib = _library(tmp_path / "lib.sqlite", [LibraryEntry((1,), 1.0, 1)])
    writer = LibraryStore.open(lib)
    try:
        writer.save_controllers(SIG, [LibraryEntry((2,), 1.0, 1)])
        assert (tmp_path / "lib.sqlite-wal").exists()
        assert main(["db", "info", str(lib)]) == 0
        assert f"{SIG}: 2 controllers" in capsys.readouterr().out
    finally:
        writer.close()


def test_sitl_config_keeps_its_library_apart_from_the_demos():
    demo_out = Path(build_parser().parse_args(["sim"]).out)
    path = Path(load_service_config(SITL_CONFIG).store.path)
    # sim writes DIR/library-K.sqlite and DIR/vehicleK/: the service of config/sitl.toml
    # must not load (and then overwrite) a demo vehicle's library
    assert path.parent != demo_out
    assert not path.is_relative_to(demo_out / "vehicle1")


def test_info_lists_signatures_and_origins(tmp_path, capsys):
    lib = _library(
        tmp_path / "lib.sqlite",
        [LibraryEntry((1,), 1.0, 1), LibraryEntry((2,), 1.0, 1, "shared:2")],
        model=b"m",
    )
    assert main(["db", "info", str(lib)]) == 0
    out = capsys.readouterr().out
    assert f"{SIG}: 2 controllers (shared 1, solved 1), 0 transitions, 1 models" in out


def test_merge_takes_a_bundled_config_by_name_and_names_a_config_it_cannot_read(tmp_path):
    # `db merge ... --config sitl` in a checkout (which has a sitl/ folder) died on an
    # IsADirectoryError traceback; `run --config sitl` takes the bundled config by name
    import subprocess
    import sys

    src = _library(tmp_path / "v1.sqlite", [LibraryEntry((), 3.0, 1), LibraryEntry((1,), 2.0, 1)])
    (tmp_path / "sitl").mkdir()
    (tmp_path / "cfgdir").mkdir()

    def db(*argv: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-m", "epc_offboard", "db", *argv]
        return subprocess.run(command, capture_output=True, text=True, timeout=180, cwd=tmp_path)

    by_name = db("merge", "fleet.sqlite", str(src), "--config", "sitl")
    assert by_name.returncode == 0, by_name.stderr
    got = _contents(tmp_path / "fleet.sqlite").signatures[SIG].controllers
    assert sorted(c.active_set for c in got) == [(), (1,)]
    unreadable = db("merge", "other.sqlite", str(src), "--config", "cfgdir/")
    assert unreadable.returncode == 2, unreadable.stderr
    assert "cfgdir: cannot read the config file: Is a directory" in unreadable.stderr
    assert "Traceback" not in unreadable.stderr
    assert not (tmp_path / "other.sqlite").exists()  # nothing written
