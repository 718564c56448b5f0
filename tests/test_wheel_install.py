"""The production install: the wheel `pip install .` builds flies from outside the checkout.

The wheel is built from a copy of the sources (no network: the dev venv's setuptools, no build
isolation) and installed with --no-deps into a fresh venv whose dependencies come from the dev
venv (a .pth line, so the dev venv's editable epc_offboard is never imported). Every command
then runs from a temporary folder with no PYTHONPATH, so only the wheel's files can answer:
the bundled configs, scenarios and the airframe (issue 22, item 1).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

from epc_offboard.common import jit
from epc_offboard.common.ports import free_port

ROOT = Path(__file__).resolve().parent.parent
SOURCES = ("pyproject.toml", "README.md", "config", "epc_offboard", "sitl")

# `epc-offboard run --config sitl` flies `epc-sitl --instance 0` on PX4 SITL's ports (UDP 14540
# and 14580). A private network namespace (unshare -rn) gives the pair a loopback of their own,
# so the bundled config flies unchanged and nothing else on the machine hears or collides;
# where user namespaces are off, the same config with link.url on a free port.
_FLY_BUNDLED = """
ip link set lo up 2>/dev/null || true
epc-sitl --instance 0 --gcs-port 0 $SITL_PORTS > sitl.log 2>&1 &
sitl=$!
epc-offboard run --config "$SERVICE_CONFIG" > service.log 2>&1 &
svc=$!
i=0
while [ $i -lt 2400 ] && ! grep -q "offboard confirmed" service.log; do
    kill -0 $svc 2>/dev/null || break; sleep 0.1; i=$((i+1))
done
kill -TERM $svc; wait $svc; rc=$?
kill -TERM $sitl; wait $sitl
exit $rc
"""


def _private_network() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rn", "true"], capture_output=True, timeout=10)
    return probe.returncode == 0


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A venv holding only the wheel (its dependencies: the dev venv's), returns its bin/."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(
                path, src / name, symlinks=True,
                ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"),
            )  # fmt: skip
        else:
            shutil.copy2(path, src / name)
    dist = tmp / "dist"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(
        [*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(dist), str(src)],
        check=True, timeout=120,
    )  # fmt: skip
    (wheel,) = dist.glob("epc_offboard-*.whl")
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True, capture_output=True, text=True,
    ).stdout.strip()  # fmt: skip
    Path(site, "dev-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run(
        [*pip, "--python", str(py), "install", "--no-deps", str(wheel)], check=True, timeout=120
    )
    return venv / "bin"


def _user_env(bin_dir: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    # numba's cache is keyed by source path: the wheel's files have a cache of their own
    env["NUMBA_CACHE_DIR"] = str(bin_dir.parent.parent / "numba-cache")
    return env


@pytest.mark.timeout(720)  # waits are safety bounds for a loaded machine
def test_the_wheel_ships_its_configs_and_flies_from_any_folder(
    wheel_venv: Path, tmp_path: Path
) -> None:
    env = _user_env(wheel_venv)
    where = subprocess.run(
        [str(wheel_venv / "python"), "-c",
         "import epc_offboard, sitl; from sitl.params import DEFAULT_VEHICLE_FILE as v; "
         "print(epc_offboard.__file__, sitl.__file__, v)"],
        cwd=tmp_path, env=env, check=True, capture_output=True, text=True,
    ).stdout.split()  # fmt: skip
    assert all(str(wheel_venv.parent) in p for p in where), where  # not the checkout's files

    sitl_help = subprocess.run(
        ["epc-sitl", "--help"], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert sitl_help.returncode == 0, sitl_help.stderr
    assert "--instance" in sitl_help.stdout

    # the service against the bundled SITL, with the bundled config named as a user would
    fly_dir = tmp_path / "run"
    fly_dir.mkdir()
    fly_env = {**env, "SERVICE_CONFIG": "sitl", "SITL_PORTS": ""}
    cmd = ["sh", "-c", _FLY_BUNDLED]
    if _private_network():
        cmd = ["unshare", "-rn", *cmd]
    else:
        port = free_port()
        raw = (Path(where[0]).parent / "data" / "sitl.toml").read_text()  # the wheel's
        (fly_dir / "sitl.toml").write_text(
            raw.replace('"udpin://127.0.0.1:14540"', f'"udpin://127.0.0.1:{port}"')
        )
        fly_env["SERVICE_CONFIG"] = "./sitl.toml"
        fly_env["SITL_PORTS"] = f"--listen-port 0 --offboard-port {port}"

    # the demo, as the README runs it, on free ports, on the kernels' numpy twins: numba's
    # compile of the wheel's files (a minute of CPU, the same sources the checkout's cache
    # compiled for this suite, tests/conftest.py) would prove nothing of the package's files
    sim_dir = tmp_path / "sim"
    sim_dir.mkdir()
    sim = subprocess.run(
        ["epc-offboard", "sim", "--gcs-port", "0", "--duration", "3.5"],
        cwd=sim_dir, env={**env, jit.ENV: "0"}, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert sim.returncode == 0, sim.stdout + sim.stderr
    report = (sim_dir / "out" / "report.json").read_text()
    assert '"scenario": "hover"' in report

    # the service starts on a cold cache, as a user's first `run` does: it flies the twins
    # and compiles the wheel's kernels in the background (service/coldstart.py)
    flight = subprocess.Popen(cmd, cwd=fly_dir, env=fly_env)
    try:
        flight_rc = flight.wait(timeout=300)
    finally:
        if flight.poll() is None:
            flight.send_signal(signal.SIGKILL)
    service_log = (fly_dir / "service.log").read_text()
    sitl_log = (fly_dir / "sitl.log").read_text()
    assert "offboard confirmed" in service_log, service_log + sitl_log
    assert flight_rc == 0, service_log  # SIGTERM: hold, save the library, exit 0


def test_the_bundled_configs_are_what_the_package_loads() -> None:
    from epc_offboard.common.bundled import bundled_config, bundled_dir, bundled_names

    assert bundled_dir().resolve() == (ROOT / "config").resolve()
    assert bundled_names() == ["default", "sitl"]
    assert bundled_config("sitl") == bundled_dir() / "sitl.toml"
    assert bundled_config("./sitl") == Path("./sitl")  # a path stays a path
    with (bundled_dir() / "sitl.toml").open("rb") as fh:
        assert tomllib.load(fh)["link"]["url"].startswith("udpin://")


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None, reason="needs systemd-sysusers")
def test_sysusers_creates_the_user_the_unit_runs_as(tmp_path: Path) -> None:
    unit = (ROOT / "config" / "epc-offboard.service").read_text()
    assert "User=epc" in unit
    assert "config/epc-offboard.sysusers" in unit  # the unit says how the user is made
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "passwd").write_text("root:x:0:0::/root:/bin/sh\n")
    (tmp_path / "etc" / "group").write_text("root:x:0:\ndialout:x:20:\n")
    subprocess.run(
        ["systemd-sysusers", f"--root={tmp_path}", str(ROOT / "config" / "epc-offboard.sysusers")],
        check=True, capture_output=True, timeout=30,
    )  # fmt: skip
    passwd = (tmp_path / "etc" / "passwd").read_text()
    assert any(line.startswith("epc:") for line in passwd.splitlines())
    assert ":/var/lib/epc-offboard:" in passwd  # the unit's StateDirectory
