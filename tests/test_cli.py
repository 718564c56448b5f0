"""The command line a user meets first: --version, and help for every flag of every command."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from epc_offboard import __version__
from epc_offboard.cli import build_parser
from epc_offboard.tools.sim.scenario import SCENARIO_DIR


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def test_version_prints_the_package_version():
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "--version"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"epc-offboard {__version__}"


@pytest.mark.parametrize("command", ["run", "sim", "bench", "db"])
def test_every_flag_has_help_and_shows_its_default(command):
    sub = _subparsers(build_parser())[command]
    text = sub.format_help()
    for action in sub._actions:
        if not action.option_strings or action.help == argparse.SUPPRESS:
            continue
        flag = action.option_strings[-1]
        assert action.help, f"{command} {flag}: no help text"
        if action.default not in (None, False, True, argparse.SUPPRESS):
            # the rendered help carries the default value itself
            assert f"default: {action.default}" in " ".join(text.split()) or (
                "default" in action.help
            ), f"{command} {flag}: default {action.default!r} not shown"


def test_sim_help_lists_every_bundled_scenario():
    text = " ".join(_subparsers(build_parser())["sim"].format_help().split())
    names = sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
    assert len(names) >= 5
    for name in names:
        assert name in text, f"scenario {name} missing from sim --help"


def test_bench_lwpr_runs_the_lwpr_benchmark(monkeypatch):
    """`epc-offboard bench --lwpr` is the LWPR benchmark's command (it was
    `python -m epc_offboard.bench_lwpr` before the package layout), its --json passed on."""
    from epc_offboard.cli import main
    from epc_offboard.tools import bench_lwpr

    seen: list[list[str] | None] = []

    def fake_main(argv: list[str] | None = None) -> int:
        seen.append(argv)
        return 0

    monkeypatch.setattr(bench_lwpr, "main", fake_main)
    assert main(["bench", "--lwpr", "--json", "x.json"]) == 0
    assert seen == [["--json", "x.json"]]


def test_bench_attack_runs_the_attack_benchmark_with_its_options(monkeypatch):
    """`epc-offboard bench --attack` is issue 21's attack benchmark (a real-time flight, too
    long for this test: its wiring only); a negative hog count is a usage error."""
    from epc_offboard.cli import main
    from epc_offboard.tools import bench_attack

    seen: list[tuple[str | None, int, str, int | None, int | None]] = []
    options: list[bench_attack.AttackOptions | None] = []

    def fake_run(json_path: str | None, hogs: int, mode: str, loops_cpu: int | None = None,
                 sitl_cpu: int | None = None,
                 opts: bench_attack.AttackOptions | None = None) -> int:  # fmt: skip
        seen.append((json_path, hogs, mode, loops_cpu, sitl_cpu))
        options.append(opts)
        return 0

    monkeypatch.setattr(bench_attack, "run_attack_bench", fake_run)
    assert main(["bench", "--attack", "--hogs", "2", "--attitude-mode", "rates",
                 "--json", "a.json", "--loops-cpu", "1", "--sitl-cpu", "0"]) == 0  # fmt: skip
    assert main(["bench", "--attack"]) == 0
    assert seen == [("a.json", 2, "rates", 1, 0), (None, 0, "quaternion", None, None)]
    assert options == [bench_attack.AttackOptions()] * 2  # issue 21's bench by default
    assert main(["bench", "--attack", "--autopilot", "ardupilot", "--attack-s", "60",
                 "--attacks", "flood+fuzz,fuzz", "--signing", "--forge", "--freeze", "store",
                 "--freeze-s", "15"]) == 0  # fmt: skip
    assert options[-1] == bench_attack.AttackOptions(
        autopilot="ardupilot", attack_s=60.0, attacks=("flood+fuzz", "fuzz"), signing=True,
        forge=True, freeze="store", freeze_s=15.0)  # fmt: skip
    assert main(["bench", "--attack", "--no-probe"]) == 0  # the machine's floor not probed
    assert options[-1] == bench_attack.AttackOptions(probe=False)
    assert main(["bench", "--attack", "--probe-priority", "51"]) == 0
    assert options[-1] == bench_attack.AttackOptions(probe_priority=51)
    for bad in (["--hogs", "-1"], ["--loops-cpu", "-1"], ["--sitl-cpu", "-1"],
                ["--freeze", "nobody"], ["--autopilot", "inav"]):  # fmt: skip
        with pytest.raises(SystemExit) as exc:
            main(["bench", "--attack", *bad])
        assert exc.value.code == 2
    # what argparse cannot check: a usage error printed, exit 1, nothing flown
    for bad in (["--attacks", "fuzz+fuzz"], ["--attacks", "flood+rotate+fuzz"],
                ["--attacks", "quake"], ["--attack-s", "0"],
                ["--probe-priority", "0"]):  # fmt: skip
        assert main(["bench", "--attack", *bad]) == 1
    assert len(options) == 5


def test_the_parser_and_sims_launcher_import_no_control_stack():
    """Every command's parser (``--help`` included) lists the scenarios without importing
    numba (0.46 -> 0.19 CPU-s for ``--help``), and ``sim``'s own process flies no
    controller: it imports neither the service's config nor OSQP (~0.7 CPU-s a flight),
    nor numba (the trajectories' kernels, for the scenario's TrajectoryConfig: 0.4 CPU-s
    a flight until stop 44). A fresh interpreter each: the modules a real start-up loads."""
    code = (
        "import sys\n"
        "from epc_offboard.cli import build_parser\n"
        "build_parser()\n"
        "assert 'numba' not in sys.modules, 'the parser imports numba'\n"
        "import epc_offboard.tools.sim.command, epc_offboard.tools.sim.orchestrate\n"
        "heavy = {'epc_offboard.service.config', 'osqp', 'numba'} & set(sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.parametrize("what", ["readme", "neuralfly"])
def test_figures_without_a_readme_says_so_before_flying_anything(tmp_path, what):
    # an installed wheel has no README: `figures` once flew every recipe (half an hour), then
    # died on a FileNotFoundError traceback; with --numbers-only at once, the same traceback
    results = tmp_path / "results"
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard", "figures", what, "--numbers-only",
         "--readme", str(tmp_path / "README.md"), "--results", str(results)],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert f"--readme {tmp_path / 'README.md'}: no such file" in proc.stderr
    assert "pip install -e ." in proc.stderr
    assert not results.exists()  # nothing written
