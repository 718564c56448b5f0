"""Every flag of `epc-offboard sim` and `epc-sitl` is checked before anything starts (issue 22,
item 5): a bad value, or a flag another makes meaningless, is exit code 2 with a message naming
the flag and the value; a taken port is named, and said before the service's kernel warm-up.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from epc_offboard.cli import main
from epc_offboard.common.cliargs import join_negative_values
from epc_offboard.common.ports import free_port
from sitl.main import main as sitl_main

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _never_fly(monkeypatch: pytest.MonkeyPatch) -> None:
    """A check that misses lets sim fly: fail at once instead of starting processes."""

    def flew(*_args: object) -> int:
        raise AssertionError("sim went on to fly despite the bad usage")

    monkeypatch.setattr("epc_offboard.tools.sim.command.run_one", flew)
    monkeypatch.setattr("epc_offboard.tools.compare.run_compare", flew)
    monkeypatch.setattr("epc_offboard.tools.sim.command.check_ports", lambda _o: None)


def says(text: str, *parts: str) -> None:
    missing = [p for p in parts if p not in text]
    assert not missing, f"{missing} not in: {text}"


def usage(command, argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    try:
        code = command(argv)
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "flag", "value"),
    [
        (["--duration", "nan"], "--duration", "nan"),
        (["--duration", "inf"], "--duration", "inf"),
        (["--duration", "2"], "--duration", "2"),  # inside hover's 3 s settle time
        (["--gcs-port", "70000"], "--gcs-port", "70000"),
        (["--gcs-port", "-1"], "--gcs-port", "-1"),
        (["--wind", "-3,45"], "--wind", "-3,45"),
        (["--wind", "3,nan"], "--wind", "3,nan"),
        (["--wind", "3"], "--wind", "3"),
        (["--wind-profile", "sine:2.4"], "--wind-profile", "sine:2.4"),
        (["--wind-profile", "sine:2.4,0"], "--wind-profile", "sine:2.4,0"),
        (["--wind-profile", "breeze"], "--wind-profile", "breeze"),
        (["--vehicles", "0"], "--vehicles", "0"),
        (["--seed", "-1"], "--seed", "-1"),
        (["--stagger"], "--stagger", "--vehicles"),
        (["--no-share"], "--no-share", "--vehicles"),
        (["--compare", "--controller", "pd"], "--controller", "pd"),
        (["--compare", "epc:kf", "--adaptation", "none"], "--adaptation", "none"),
        (["--autopilot", "ardupilot", "--gcs-port", "65530", "--vehicles", "2"],
         "--gcs-port", "65540"),
        (["--json", "/nonexistent-dir/r.json"], "--json", "/nonexistent-dir"),
        (["--out", "pyproject.toml"], "--out", "pyproject.toml"),
    ],
)  # fmt: skip
def test_sim_rejects_bad_flags_naming_flag_and_value(
    argv: list[str], flag: str, value: str, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(ROOT)
    code, err = usage(main, ["sim", *argv], capsys)
    assert code == 2, err
    says(err, flag, value)
    assert "Traceback" not in err


def test_a_negative_wind_names_the_wind_it_means(capsys: pytest.CaptureFixture[str]) -> None:
    _, err = usage(main, ["sim", "--wind", "-3,45"], capsys)
    assert "3,225" in err  # 3 m/s towards 225 deg is that wind
    assert "expected one argument" not in err


def test_valid_combinations_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    from epc_offboard.cli import build_parser
    from epc_offboard.tools.sim.options import sim_options

    def options(*argv: str):
        return sim_options(build_parser().parse_args(["sim", *argv]))

    assert options("--vehicles", "2", "--stagger", "--no-share").stagger
    assert options("--compare", "pd:none").compare == ("pd:none",)
    assert options("--controller", "pd").controller == "pd"
    assert (options().controller, options().adaptation) == ("epc", "lwpr")
    assert options("--wind", "0,-90").wind == (0.0, -90.0)
    assert options("--wind-profile", "sine:2.4,1").wind_profile.text == "sine:2.4,1"
    assert options().wind_profile.text == "steady"
    assert options("--gcs-port", "0").gcs_port == 0


def test_negative_values_are_joined_only_after_the_flags_that_take_them() -> None:
    argv = ["sim", "--wind", "-3,45", "--seed", "1", "--wind", "--x"]
    assert join_negative_values(argv, ("--wind",)) == [
        "sim", "--wind=-3,45", "--seed", "1", "--wind", "--x"]  # fmt: skip


@pytest.mark.parametrize(
    ("argv", "flag", "value"),
    [
        (["--instance", "300"], "--instance", "300"),
        (["--instance", "-1"], "--instance", "-1"),
        (["--wind", "-3,45"], "--wind", "-3,45"),
        (["--wind-profile", "gusts:-1,2"], "--wind-profile", "gusts:-1,2"),
        (["--speedup", "nan"], "--speedup", "nan"),
        (["--speedup", "0"], "--speedup", "0"),
        (["--listen-port", "70000"], "--listen-port", "70000"),
        (["--offboard-port", "65536"], "--offboard-port", "65536"),
        (["--gcs-port", "70000"], "--gcs-port", "70000"),
        (["--lockstep-timeout-ms", "inf"], "--lockstep-timeout-ms", "inf"),
        (["--lockstep-period-ms", "0"], "--lockstep-period-ms", "0"),
        (["--duration", "nan"], "--duration", "nan"),
        (["--seed", "-1"], "--seed", "-1"),
    ],
)
def test_sitl_rejects_bad_flags_naming_flag_and_value(
    argv: list[str], flag: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, err = usage(sitl_main, argv, capsys)
    assert code == 2, err
    says(err, flag, value)


def test_sitl_names_a_taken_port(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        code, err = usage(
            sitl_main, ["--listen-port", str(port), "--gcs-port", "0", "--duration", "0.1"], capsys
        )
    assert code == 1
    says(err, f"127.0.0.1:{port}", "--listen-port", "in use")


def test_sim_names_a_taken_port_before_starting_anything(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from epc_offboard.tools.sim import command, orchestrate

    monkeypatch.setattr(command, "check_ports", orchestrate.check_ports)  # the real one
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = ["sim", "--autopilot", "ardupilot", "--gcs-port", str(port),
                "--out", str(tmp_path / "out")]  # fmt: skip
        code, err = usage(main, argv, capsys)
    assert code == 1
    says(err, f"127.0.0.1:{port}", "--gcs-port", "in use")
    assert not (tmp_path / "out" / "vehicle1").exists()  # nothing started


def run_service(tmp_path: Path, url: str) -> subprocess.CompletedProcess[str]:
    """A real `epc-offboard run` of config/sitl.toml on link ``url``, its library in
    ``tmp_path``, its config ``tmp_path/service.toml``; to its end (a bad start ends it)."""
    config = (ROOT / "config" / "sitl.toml").read_text()
    config = config.replace("udpin://127.0.0.1:14540", url)
    config = config.replace("out/sitl-service/library.sqlite", str(tmp_path / "lib.sqlite"))
    (tmp_path / "service.toml").write_text(config)
    return subprocess.run(
        [sys.executable, "-m", "epc_offboard", "run", "--config", str(tmp_path / "service.toml")],
        capture_output=True, text=True, timeout=180,
    )  # fmt: skip


def test_the_service_names_a_taken_port_before_its_warm_up(tmp_path: Path) -> None:
    port = free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", port))
        proc = run_service(tmp_path, f"udpin://127.0.0.1:{port}")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    says(out, f"127.0.0.1:{port}", "link.url", "in use")
    assert "compiled and warmed" not in out  # said before the ~4 s of warm-up, not after


def test_sim_through_a_fleet_router_shares_as_clients_with_no_fixed_port() -> None:
    from epc_offboard.cli import build_parser
    from epc_offboard.common.errors import UsageError
    from epc_offboard.tools.sim.options import sim_options
    from epc_offboard.tools.sim.orchestrate import _sharing_flags

    def options(*argv: str):
        return sim_options(build_parser().parse_args(["sim", *argv]))

    ep = "tcp/127.0.0.1:24447"
    flags = _sharing_flags(options("--fleet-router", ep), 1)  # one vehicle shares too
    assert flags["mode"] == "client"
    assert flags["connect"] == [ep]
    assert "listen" not in flags
    assert _sharing_flags(options("--vehicles", "2"), 1)["listen"]  # peers: as before
    with pytest.raises(UsageError, match="--fleet-router with --no-share"):
        options("--vehicles", "2", "--fleet-router", ep, "--no-share")


@pytest.mark.parametrize(
    ("url", "says_what"),
    [("udp:/127.0.0.1:14540", "scheme must be"), ("udpin://127.0.0.1:99999", "bad port")],
)
def test_the_service_names_a_bad_link_url_with_its_key_and_file(
    tmp_path: Path, url: str, says_what: str
) -> None:
    # it said "connection url ...: bad port" with neither the key nor the file (README: a bad
    # value stops the service with exit code 2 and a message naming the key and the file)
    proc = run_service(tmp_path, url)
    assert proc.returncode == 2, proc.stderr
    says(proc.stderr, str(tmp_path / "service.toml"), "`link`", "url", url, says_what)
    assert "Traceback" not in proc.stderr


def test_the_service_names_a_serial_device_it_cannot_open(tmp_path: Path) -> None:
    # it said "epc-offboard: [Errno 2] No such file or directory: '/.../ttyNONE'", naming
    # neither link.url nor what it was doing; exit 1 stays (a USB adapter may enumerate
    # late: the unit's Restart=on-failure tries again)
    device = tmp_path / "ttyNONE"
    proc = run_service(tmp_path, f"serial://{device}:921600")
    assert proc.returncode == 1, proc.stderr
    says(proc.stderr, f"link.url serial://{device}:921600: cannot open",
         "No such file or directory")  # fmt: skip
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize(
    ("argv", "command", "hint"),
    [(["sim", "--scenaro", "hover"], "sim", "--scenaro: did you mean --scenario?"),
     (["bench", "--stpes", "3"], "bench", "--stpes: did you mean --steps?"),
     (["sim", "--gcs-prot=0"], "sim", "--gcs-prot: did you mean --gcs-port?")],
)  # fmt: skip
def test_a_mistyped_flag_gets_its_commands_usage_and_the_flag_it_meant(
    argv: list[str], command: str, hint: str
) -> None:
    # it printed the top-level usage ("epc-offboard [-h] [--version] COMMAND ...") and no hint
    proc = subprocess.run([sys.executable, "-m", "epc_offboard", *argv], capture_output=True,
                          text=True, timeout=60, cwd=ROOT)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    says(proc.stderr, f"usage: epc-offboard {command} ", f"epc-offboard {command}: error: "
         "unrecognized arguments", hint)  # fmt: skip
