"""`epc-offboard bench --attack`: issue 21's attacks on one real-time flight, and its targets.

One flight on the bundled SITL (PX4 personality, SIH drag, real time, the figure-8
scenario's 3 m/s wind) and the service as its own process, as deployed (nice -5, the loops
SCHED_FIFO at ``realtime_priority`` 50 as config/default.toml asks, where permitted; the
SITL SCHED_FIFO at 40: it stands in for an autopilot with a processor of its own). The vehicle
hovers, then flies the windy figure-8 (the trajectory switched by SIGHUP, as a user reloads
it). In each phase every attack runs for ``WINDOW_S`` in a window of its own, with
``GAP_S`` of calm before it (measured too, as the baseline):

* ``flood``: one Zenoh peer id sending 1,000 well-formed, useless 400-controller batches a
  second;
* ``rotate``: the same from 100 rotating ids;
* ``replay``: genuine, valid controllers (solved as a peer would) recorded once as 8 peers'
  batches and sent again and again, 1,000 a second;
* ``flap``: liveliness tokens of rotating ids declared and undeclared, 1,000 changes a second;
* ``fuzz``: 2,000 datagrams a second of fuzzed MAVLink to the service's port
  (:mod:`epc_offboard.tools.fuzz_mavlink`).

The Zenoh attackers are processes of their own (:mod:`epc_offboard.tools.zenoh_attack`), each
with a real session connected to the service's listening endpoint on loopback (multicast
scouting off). ``--hogs N`` runs N CPU hogs (``python3 -c 'while 1: pass'``) for the
flight, killed by PID after it.

Measured per window (:mod:`epc_offboard.tools.attack_analysis`): the position loop's longest
gap and its ticks' compute (the flight log's ``compute_us``), the attitude loop's rate, late
ticks and mode (its SET_ATTITUDE_TARGET sends in the tlog), error to the reference and
altitude loss (the SITL's ground truth), the time in offboard (the ground truth's mode), the
control process's RSS and the helpers' CPU (sampled from /proc every 0.25 s), the load.
With ``--attitude-mode rates`` the windy figure-8 is also flown in lockstep afterwards (its
RMSE is what the real-time body-rate flight is judged against). Writes the JSON report and
a figure (FILE.png), prints each window and each of issue 21's targets with a verdict
computed from this run.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from epc_offboard.common.children import launched_env
from epc_offboard.common.configio import dump_toml, merge_dicts
from epc_offboard.common.errors import EpcError
from epc_offboard.common.ports import free_port
from epc_offboard.common.procstats import StartWatch, stat_fields
from epc_offboard.tools import attack_analysis as analysis
from epc_offboard.tools import floor_probe
from epc_offboard.tools import steal as steal_time
from epc_offboard.tools.bench_modes import start_hogs, stop_hogs
from epc_offboard.tools.sim.analysis import read_csv_columns
from epc_offboard.tools.sim.orchestrate import service_env, stop_process, vehicle_file
from epc_offboard.tools.sim.scenario import SITL_SERVICE_CONFIG, load_scenario

WINDOW_S = 10.0
GAP_S = 5.0  # calm before each attack; its last CALM_S are the calm window
CALM_S = 4.0
SETTLE_S = 5.0  # offboard hover before the first window
FIGURE8_SETTLE_S = 8.0  # the figure-8's ramp (3 s) and the scenario's settle time
ZENOH_ATTACKS = ("flood", "rotate", "replay", "flap")
ATTACKS = (*ZENOH_ATTACKS, "fuzz")
# ``--attacks``: any of ATTACKS, or two joined by "+" run at once (e.g. "flood+fuzz")
# --freeze: which helper process, or the autopilot itself ("sitl": its link silent, as a
# radio drop-out or a frozen autopilot, while the attack goes on)
HELPERS = ("fleet", "store", "miss", "log", "pump", "sitl")
FREEZE_S = 20.0  # --freeze: how long the helper stays SIGSTOPped
AUTOPILOTS = ("px4", "ardupilot")
ZENOH_RATE_PER_S = 1000.0
FUZZ_RATE_HZ = 2000.0
REALTIME_PRIORITY = 50  # config/default.toml's
SITL_FIFO_PRIORITY = 40  # below the service's loops: an autopilot never waits for them
SERVICE_SYSTEM_ID = 245  # link.system_id's default: the sender of the attitude setpoints
FLEET = "bench"
MODES = {"quaternion": "autopilot", "rates": "auto"}  # --attitude-mode -> attitude.mode
SAMPLE_S = 0.25
# an attacker's start: failed once it used and waited for no CPU this long, or not ready in
# the cap though running (Attackers.wait_ready)
ATTACKER_STALL_S = 30.0
ATTACKER_CAP_S = 900.0


@dataclass(frozen=True)
class AttackOptions:
    """What ``bench --attack`` varies beyond the hogs and the attitude mode (the defaults:
    issue 21's bench). ``autopilot``: the SITL's personality (ardupilot: GUIDED,
    GUID_OPTIONS=8, as sim flies it); ``attack_s``: each attack's length; ``attacks``: which
    attacks, in order, each a name of ATTACKS or two joined by "+" (run at once);
    ``signing``: a fresh MAVLink 2 signing key for the service and the SITL (the fuzzer does
    not have it); ``forge``: the fuzzer also forges the vehicle's state (fuzz_mavlink
    ``--forge``); ``freeze``: one helper process (HELPERS) SIGSTOPped for ``freeze_s`` from
    the start of each phase's first attack, then SIGCONT; ``probe``: the machine's floor
    measured beside the loops (:class:`Probes`; ``--no-probe`` turns it off) at
    ``probe_priority`` (SCHED_FIFO; by default the loops')."""

    autopilot: str = "px4"
    attack_s: float = WINDOW_S
    attacks: tuple[str, ...] = ATTACKS
    signing: bool = False
    forge: bool = False
    freeze: str | None = None
    freeze_s: float = FREEZE_S
    probe: bool = True
    probe_priority: int = REALTIME_PRIORITY

    def __post_init__(self) -> None:
        if self.autopilot not in AUTOPILOTS:
            raise AttackBenchError(f"--autopilot: one of {', '.join(AUTOPILOTS)}")
        if not 1.0 <= self.attack_s <= 600.0:
            raise AttackBenchError("--attack-s: 1 to 600 s")
        if not self.attacks:
            raise AttackBenchError("--attacks: at least one")
        for name in self.attacks:
            parts = name.split("+")
            if len(parts) > 2 or len(set(parts)) != len(parts) or not set(parts) <= set(ATTACKS):
                raise AttackBenchError(
                    f"--attacks: {name!r} is not one of {', '.join(ATTACKS)} "
                    "or two of them joined by '+'")  # fmt: skip
        if self.freeze is not None and self.freeze not in HELPERS:
            raise AttackBenchError(f"--freeze: one of {', '.join(HELPERS)}")
        if self.freeze_s <= 0.0:
            raise AttackBenchError("--freeze-s must be > 0")
        if not 1 <= self.probe_priority <= 99:
            raise AttackBenchError("--probe-priority: 1 to 99")


def parse_attacks(text: str) -> tuple[str, ...]:
    """``--attacks``' comma-separated list (validated by AttackOptions)."""
    return tuple(a.strip() for a in text.split(",") if a.strip())


class AttackBenchError(EpcError, RuntimeError):
    pass


def _deployed_priority() -> None:
    floor_probe.schedule(None, None)


def _autopilot_scheduling(cpu: int | None) -> Any:
    """The SITL's ``preexec_fn``: it stands in for an autopilot on a processor of its own,
    SCHED_FIFO below the service's loops where permitted (else the deployed nice), and with
    ``cpu`` pinned to that CPU (``--sitl-cpu``; a CPU not offered: left unpinned). At
    normal priority beside two hogs and a load of 20-30 its simulated clock fell up to 0.3 s
    behind the wall clock and caught up in a sprint: the service rightly judged its samples
    stale and failed safe, in calm windows as in attacks, which measured the simulator's
    starvation, not the service."""

    def scheduling() -> None:
        floor_probe.schedule(SITL_FIFO_PRIORITY, cpu)

    return scheduling


def service_config(run_dir: Path, port: int, zenoh_port: int, mode: str,
                   loops_cpu: int | None = None, autopilot: str = "px4",
                   signing_key_file: Path | None = None) -> dict[str, Any]:  # fmt: skip
    """config/sitl.toml + what the bench flies: real time, the deployed scheduling, a hover
    to begin with (the figure-8 comes by SIGHUP), every log, fleet sharing listening on
    ``zenoh_port``; ``loops_cpu``: the loops pinned to that CPU; ``autopilot``: the
    personality flown; ``signing_key_file``: MAVLink signing on with that key."""
    with SITL_SERVICE_CONFIG.open("rb") as fh:
        base = tomllib.load(fh)
    scenario = load_scenario("figure8")
    return merge_dicts(base, {
        "link": {"url": f"udpin://127.0.0.1:{port}", "autopilot": autopilot,
                 "signing_key_file": str(signing_key_file or "")},
        "loops": {"clock": "wall", "realtime_priority": REALTIME_PRIORITY,
                  "cpu_affinity": [] if loops_cpu is None else [loops_cpu]},
        "attitude": {"mode": MODES[mode]},
        "trajectory": {"shape": "hover"},
        "trajectory_altitude_m": scenario.altitude_m,
        "mission": {"duration_s": 100_000.0, "land_at_end": True},  # ended by the bench
        "store": {"path": str(run_dir / "library.sqlite")},
        "log": {"flight_log_path": str(run_dir / "flight.csv"),
                "tlog_path": str(run_dir / "session.tlog"),
                "stats_path": str(run_dir / "stats.json")},
        "sharing": {"enabled": True, "fleet": FLEET, "vehicle_id": "victim",
                    "listen": [f"tcp/127.0.0.1:{zenoh_port}"], "scouting_multicast": False},
    })  # fmt: skip


def figure8_config(cfg: dict[str, Any]) -> dict[str, Any]:
    traj = {k: v for k, v in vars(load_scenario("figure8").trajectory).items()}
    traj["waypoints_ned_m"] = [list(w) for w in traj["waypoints_ned_m"]]
    return merge_dicts(cfg, {"trajectory": traj})


# -- the processes' resources, from /proc ---------------------------------------------------


def _stat(pid: int) -> tuple[float, float] | None:
    """(CPU seconds, RSS MB) of ``pid``, None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat_fields(text)
    tick = os.sysconf("SC_CLK_TCK")
    rss_mb = int(fields[21]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    return (int(fields[11]) + int(fields[12])) / tick, rss_mb


def _pinned(pid: int, cpu: int | None) -> bool:
    """Whether ``pid`` runs on ``cpu`` alone (False without a ``cpu``)."""
    if cpu is None:
        return False
    with contextlib.suppress(OSError):
        return os.sched_getaffinity(pid) == {cpu}
    return False


def _is_fifo(pid: int) -> bool:
    with contextlib.suppress(OSError):
        return os.sched_getscheduler(pid) == os.SCHED_FIFO
    return False


def _children(pid: int) -> list[int]:
    out: list[int] = []
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


class Sampler(threading.Thread):
    """Every SAMPLE_S: the control process's CPU and RSS, its children's CPU, the load."""

    def __init__(self, pid: int) -> None:
        super().__init__(name="sampler", daemon=True)
        self.pid = pid
        self.samples: list[dict[str, Any]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(SAMPLE_S):
            control = _stat(self.pid)
            if control is None:
                return
            children = {}
            for child in _children(self.pid):
                st = _stat(child)
                if st is not None:
                    children[child] = st[0]
            self.samples.append({
                "t_s": time.monotonic(), "control_cpu_s": control[0],
                "control_rss_mb": round(control[1], 2), "children_cpu_s": children,
                "load_avg": os.getloadavg(),
            })  # fmt: skip


class Probes:
    """The machine's floor (:mod:`~epc_offboard.tools.floor_probe`): one bare 200 Hz loop
    per way of waiting, each a process of its own at the loops' scheduling (SCHED_FIFO at
    ``priority``, pinned to ``cpu`` if the loops are), started before the flight and stopped
    after it; each writes its ticks to ``run_dir/probe-WAKE.f64``."""

    def __init__(self, run_dir: Path, priority: int, cpu: int | None) -> None:
        self.paths = {w: run_dir / f"probe-{w}.f64" for w in floor_probe.WAKES}
        self.procs: dict[str, subprocess.Popen[str]] = {}
        for wake, path in self.paths.items():
            path.unlink(missing_ok=True)
            cmd = [sys.executable, "-m", "epc_offboard.tools.floor_probe", "--wake", wake,
                   "--out", str(path), "--fifo", str(priority)]  # fmt: skip
            if cpu is not None:
                cmd += ["--cpu", str(cpu)]
            with (run_dir / f"probe-{wake}.log").open("w") as log_fh:  # the child's copy
                self.procs[wake] = subprocess.Popen(
                    cmd, stdout=subprocess.PIPE, stderr=log_fh, text=True,
                    env=dict(os.environ, **launched_env()))  # ends with the bench, even killed
        self.ready: dict[str, dict[str, Any]] = {}

    def wait_ready(self, wake: str) -> dict[str, Any]:
        """``wake``'s probe's ready line (its wake, pid, whether SCHED_FIFO was applied),
        waited for; {} if it ended without one."""
        if wake not in self.ready:
            stdout = self.procs[wake].stdout
            line = stdout.readline() if stdout is not None else ""
            self.ready[wake] = json.loads(line[6:]) if line.startswith("ready ") else {}
        return self.ready[wake]

    def close(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """Stopped (SIGTERM: each writes its records); each one's ready line, its records'
        path (``path``), exit code (``exit``) and cost (its ``done`` line: ``cpu_s``,
        ``wall_s``, ``ticks``, and ``cpu_share``, the CPU over the wall), by wake."""
        for proc in self.procs.values():
            with contextlib.suppress(OSError):
                proc.send_signal(signal.SIGTERM)
        out: dict[str, Any] = {}
        for wake, proc in self.procs.items():
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            meta = dict(self.wait_ready(wake), path=str(self.paths[wake]), exit=proc.returncode)
            rest = proc.stdout.read() if proc.stdout is not None else ""
            done = next((x for x in rest.splitlines() if x.startswith("done ")), "")
            if done:  # its CPU time over its ticking time: what it cost the machine
                cost = json.loads(done[5:])
                meta.update(cost, cpu_share=round(cost["cpu_s"] / max(cost["wall_s"], 1e-9), 4))
            out[wake] = meta
        return out


# -- the flight -------------------------------------------------------------------------------


class Attackers:
    """The Zenoh attackers, one process each, prepared and connected before the flight."""

    def __init__(self, zenoh_port: int, config_path: Path, log_dir: Path,
                 kinds: tuple[str, ...] = ZENOH_ATTACKS, window_s: float = WINDOW_S,
                 ) -> None:  # fmt: skip
        self.procs: dict[str, subprocess.Popen[str]] = {}
        self.window_s = window_s
        for kind in kinds:
            self.procs[kind] = subprocess.Popen(
                [sys.executable, "-m", "epc_offboard.tools.zenoh_attack", kind,
                 "--connect", f"tcp/127.0.0.1:{zenoh_port}", "--fleet", FLEET,
                 "--config", str(config_path), "--rate", str(ZENOH_RATE_PER_S),
                 "--duration", str(window_s)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                stderr=(log_dir / f"attacker-{kind}.log").open("w"), text=True,
            )  # fmt: skip

    def wait_ready(self, stall_s: float = ATTACKER_STALL_S, cap_s: float = ATTACKER_CAP_S,
                   service_pid: int | None = None) -> None:  # fmt: skip
        """Each attacker's "ready", judged by its progress (``procstats.StartWatch``): one
        alive and running or queued for a CPU is starting (at load 12-17 its imports took
        longer than the 120 s the wait gave before stop 41); one that used and waited for
        no CPU for ``stall_s`` (SIGSTOPped, blocked), or not ready in ``cap_s``, fails the
        bench with the cause. An attacker's session waits for the service's fleet helper
        (``service_pid``'s tree): while that makes progress, so does the attacker's start."""
        for kind, proc in self.procs.items():
            assert proc.stdout is not None
            watch = StartWatch(proc.pid, stall_s, cap_s, waits_on=service_pid)
            while not select.select([proc.stdout], [], [], 0.5)[0]:
                why = watch.verdict()
                if why is not None:
                    raise AttackBenchError(f"the {kind} attacker did not start: {why}")
            line = proc.stdout.readline()
            if line.strip() != "ready":
                raise AttackBenchError(f"the {kind} attacker did not start ({line!r})")

    def attack(self, kind: str) -> dict[str, Any]:
        proc = self.procs[kind]
        assert proc.stdin is not None
        proc.stdin.write("go\n")
        proc.stdin.flush()
        line = _readline(proc.stdout, self.window_s + 30.0)
        if not line:
            raise AttackBenchError(f"the {kind} attacker ended early")
        summary: dict[str, Any] = json.loads(line)
        return summary

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.stdin is not None:
                with contextlib.suppress(OSError):
                    proc.stdin.close()
        for proc in self.procs.values():
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _readline(stream: IO[str] | None, timeout_s: float) -> str:
    """A line from a child's stdout, "" on EOF or after ``timeout_s``."""
    assert stream is not None
    out: list[str] = []
    reader = threading.Thread(target=lambda: out.append(stream.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    return out[0] if out else ""


def fuzz(port: int, window_s: float = WINDOW_S, forge: bool = False) -> dict[str, Any]:
    proc = subprocess.run(
        [sys.executable, "-m", "epc_offboard.tools.fuzz_mavlink", "--port", str(port),
         "--rate", str(FUZZ_RATE_HZ), "--duration", str(window_s),
         *(["--forge"] if forge else [])],
        capture_output=True, text=True, timeout=window_s + 30, check=True,
    )  # fmt: skip
    summary: dict[str, Any] = json.loads(proc.stdout)
    return summary


def attack(name: str, port: int, attackers: Attackers, opts: AttackOptions) -> dict[str, Any]:
    """Run attack ``name`` (one of ATTACKS, or two joined by "+", run at once in threads)
    for ``opts.attack_s``; the attacker's summary (a joint one: the first start, the longest
    duration, each part's summary under its name)."""
    def one(kind: str) -> dict[str, Any]:
        return fuzz(port, opts.attack_s, opts.forge) if kind == "fuzz" else attackers.attack(kind)

    kinds = name.split("+")
    if len(kinds) == 1:
        return one(name)
    parts: dict[str, dict[str, Any]] = {}
    errors: list[BaseException] = []

    def run(kind: str) -> None:
        try:
            parts[kind] = one(kind)
        except BaseException as exc:  # re-raised below, in the caller's thread
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(k,), daemon=True) for k in kinds]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    start = min(float(p.get("start_monotonic_s", time.monotonic())) for p in parts.values())
    end = max(float(p.get("start_monotonic_s", start)) + float(p["duration_s"])
              for p in parts.values())  # fmt: skip
    return {"start_monotonic_s": start, "duration_s": end - start, "parts": parts}


# -- a helper process frozen (--freeze) -----------------------------------------------------


def _open_files(pid: int) -> list[str]:
    out: list[str] = []
    with contextlib.suppress(OSError):
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            with contextlib.suppress(OSError):
                out.append(os.readlink(fd))
    return out


def _threads(pid: int) -> int:
    with contextlib.suppress(OSError):
        return len(list(Path(f"/proc/{pid}/task").iterdir()))
    return 0


def helper_pids(service_pid: int, run_dir: Path) -> dict[str, int]:
    """The service's helper processes by name, told apart by what they hold (the service's
    stats name their pids only at the end): ``pump`` the log pump (`common.logpipe`),
    ``store`` the library's writer (the library open), ``log`` the flight-log and tlog
    writer (flight.csv open), ``fleet`` the Zenoh session (its sockets and threads),
    ``miss`` the miss worker (the other spawned helper)."""
    out: dict[str, int] = {}
    spawned: list[int] = []
    for pid in _children(service_pid):
        with contextlib.suppress(OSError):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            if "epc_offboard.common.logpipe" in cmd:
                out["pump"] = pid
            elif "spawn_main" in cmd:
                spawned.append(pid)
    rest = []
    for pid in spawned:
        files = _open_files(pid)
        if any(f.endswith(".sqlite") for f in files):
            out["store"] = pid
        elif str(run_dir / "flight.csv") in files:
            out["log"] = pid
        else:
            rest.append(pid)
    if len(rest) > 1:  # the Zenoh session's sockets, then its runtime's threads
        fleet = max(rest, key=lambda p: (sum(f.startswith("socket:") for f in _open_files(p)),
                                         _threads(p)))  # fmt: skip
        out["fleet"] = fleet
        rest.remove(fleet)
    if rest:
        out["miss"] = rest[0]
    return out


class Freezer:
    """``--freeze``: SIGSTOP one helper for ``seconds``, then SIGCONT (in a timer thread, so
    that the attack runs meanwhile); each freeze recorded (pid, wall span, found or not)."""

    def __init__(self, helper: str, seconds: float, service_pid: int, run_dir: Path,
                 sitl_pid: int | None = None) -> None:  # fmt: skip
        self.helper, self.seconds = helper, seconds
        self.service_pid, self.run_dir, self.sitl_pid = service_pid, run_dir, sitl_pid
        self.events: list[dict[str, Any]] = []
        self._timers: list[threading.Timer] = []
        self._stopped: set[int] = set()

    def freeze(self, phase: str) -> None:
        pid = (self.sitl_pid if self.helper == "sitl"
               else helper_pids(self.service_pid, self.run_dir).get(self.helper))  # fmt: skip
        event: dict[str, Any] = {"phase": phase, "helper": self.helper, "pid": pid,
                                 "t0_s": time.monotonic(), "t1_s": None}  # fmt: skip
        self.events.append(event)
        if pid is None:
            return
        try:
            os.kill(pid, signal.SIGSTOP)
        except OSError:
            event["pid"] = None
            return
        self._stopped.add(pid)
        timer = threading.Timer(self.seconds, self._thaw, args=(pid, event))
        timer.daemon = True
        self._timers.append(timer)
        timer.start()

    def _thaw(self, pid: int, event: dict[str, Any]) -> None:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGCONT)
        self._stopped.discard(pid)
        event["t1_s"] = time.monotonic()

    def close(self) -> None:
        """Thaw now whatever is still frozen (before the service is stopped)."""
        for timer in self._timers:
            timer.cancel()
        for event in self.events:
            if event["pid"] in self._stopped:
                self._thaw(event["pid"], event)


def wait_offboard(flight_csv: Path, settle_s: float, service: subprocess.Popen[bytes],
                  timeout_s: float = 180.0) -> None:  # fmt: skip
    """Until the flight log shows ``settle_s`` of offboard ticks in a row."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if service.poll() is not None:
            raise AttackBenchError(f"the service exited with {service.returncode}")
        with contextlib.suppress(OSError, RuntimeError, KeyError):
            cols = read_csv_columns(flight_csv)
            phase, t_s = cols["phase"], cols["t_s"]
            off = np.flatnonzero(phase != "offboard")
            since = t_s[off[-1] + 1] if off.size and off[-1] + 1 < t_s.size else (
                t_s[0] if not off.size else None)  # fmt: skip
            if since is not None and time.monotonic() - since >= settle_s:
                return
        time.sleep(0.5)
    raise AttackBenchError(f"no {settle_s:g} s of offboard within {timeout_s:g} s")


def _stop(proc: subprocess.Popen[bytes] | None, timeout_s: float = 10.0) -> int | None:
    """sim's stop (SIGTERM, then SIGKILL); the exit code, None if never started."""
    stop_process(proc, timeout_s)
    return None if proc is None else proc.returncode


def fly(run_dir: Path, hogs: int, mode: str, loops_cpu: int | None = None,
        sitl_cpu: int | None = None, opts: AttackOptions | None = None,
        ) -> dict[str, Any]:  # fmt: skip
    """The flight and its windows; returns the raw record (windows, samples, ports)."""
    opts = opts or AttackOptions()
    port, sitl_port = free_port(), free_port()
    zenoh_port = free_port()
    key_file = None
    if opts.signing:
        key_file = run_dir / "signing.key"
        key_file.write_bytes(os.urandom(32))
        key_file.chmod(0o600)
    cfg = service_config(run_dir, port, zenoh_port, mode, loops_cpu, opts.autopilot, key_file)
    config_path = run_dir / "service.toml"
    config_path.write_text(dump_toml(cfg))
    scenario = load_scenario("figure8")
    sitl_cmd = [sys.executable, "-m", "sitl.main", "--listen-port", str(sitl_port),
                "--offboard-port", str(port), "--gcs-port", "0",
                "--groundtruth", str(run_dir / "groundtruth.csv"), "--autopilot", opts.autopilot,
                "--config", str(vehicle_file(cfg)),
                "--wind", f"{scenario.wind_speed_m_s},{scenario.wind_dir_deg}"]  # fmt: skip
    if opts.autopilot == "ardupilot":  # as sim flies it: thrust as throttle (the README's)
        sitl_cmd += ["--param", "GUID_OPTIONS=8"]
    if key_file is not None:
        sitl_cmd += ["--signing-key", str(key_file)]
    # the service and the SITL end with the bench, even SIGKILLed (as `sim`'s do)
    env = dict(os.environ, PYTHONUNBUFFERED="1", **service_env(), **launched_env())
    hog_procs: list[subprocess.Popen[bytes]] = []
    service = sitl = None
    attackers: Attackers | None = None
    sampler: Sampler | None = None
    freezer: Freezer | None = None
    stealer: steal_time.StealSampler | None = None
    probes: Probes | None = None
    probed: dict[str, Any] = {}
    windows: list[analysis.Window] = []
    sitl_fifo = sitl_pinned = False
    load_start = os.getloadavg()
    try:
        service = subprocess.Popen(
            [sys.executable, "-m", "epc_offboard.cli", "run", "--config", str(config_path)],
            stdout=(run_dir / "service.log").open("wb"), stderr=subprocess.STDOUT, env=env,
            preexec_fn=_deployed_priority,
        )  # fmt: skip
        sitl = subprocess.Popen(
            sitl_cmd, stdout=(run_dir / "sitl.log").open("wb"), stderr=subprocess.STDOUT,
            preexec_fn=_autopilot_scheduling(sitl_cpu),
        )  # fmt: skip
        sitl_fifo = _is_fifo(sitl.pid)
        sitl_pinned = _pinned(sitl.pid, sitl_cpu)
        if opts.probe:
            probes = Probes(run_dir, opts.probe_priority, loops_cpu)
        zenoh_kinds = tuple(k for k in ZENOH_ATTACKS
                            if any(k in a.split("+") for a in opts.attacks))  # fmt: skip
        attackers = Attackers(zenoh_port, config_path, run_dir, zenoh_kinds, opts.attack_s)
        hog_procs = start_hogs(hogs)
        sampler = Sampler(service.pid)
        sampler.start()
        stealer = steal_time.StealSampler(service.pid)  # its loops run on its main thread
        stealer.start()
        attackers.wait_ready(service_pid=service.pid)
        wait_offboard(run_dir / "flight.csv", SETTLE_S, service)
        if opts.freeze is not None:
            freezer = Freezer(opts.freeze, opts.freeze_s, service.pid, run_dir, sitl.pid)
        for phase in ("hover", "figure8"):
            if phase == "figure8":
                config_path.write_text(dump_toml(figure8_config(cfg)))
                service.send_signal(signal.SIGHUP)
                time.sleep(FIGURE8_SETTLE_S)
            for i, kind in enumerate(opts.attacks):
                t_calm = time.monotonic()
                time.sleep(GAP_S)
                windows.append(analysis.Window(phase, "calm", t_calm + GAP_S - CALM_S,
                                               time.monotonic(), {}))  # fmt: skip
                if service.poll() is not None:
                    raise AttackBenchError(f"the service exited with {service.returncode}")
                t0 = time.monotonic()
                if freezer is not None and i == 0:
                    freezer.freeze(phase)
                summary = attack(kind, port, attackers, opts)
                start = float(summary.get("start_monotonic_s", t0))
                end = start + float(summary["duration_s"])
                windows.append(analysis.Window(phase, kind, start, end, summary))
        if freezer is not None:  # a freeze longer than the attacks: until it is over
            time.sleep(max(0.0, freezer.events[-1]["t0_s"] + opts.freeze_s - time.monotonic()))
        time.sleep(2.0)
        load_end = os.getloadavg()
        if freezer is not None:
            freezer.close()
            time.sleep(1.0)
        code = _stop(service)  # holds the vehicle, writes its stats
    finally:
        if probes is not None:
            probed = probes.close()
        if freezer is not None:
            freezer.close()  # a frozen helper would hold the service's stop
        stop_hogs(hog_procs)  # by PID, first: the rest stops faster without them
        if sampler is not None:
            sampler.stop.set()
        if stealer is not None:
            stealer.stop.set()
        if attackers is not None:
            attackers.close()
        _stop(service)
        _stop(sitl)
    return {"windows": windows, "samples": sampler.samples if sampler else [],
            "service_exit": code, "load_avg": {"start": load_start, "end": load_end},
            "steal": stealer.record() if stealer else {},
            "fifo_priority": REALTIME_PRIORITY, "sitl_fifo": sitl_fifo,
            "loops_cpu": loops_cpu, "sitl_cpu": sitl_cpu,
            "sitl_cpu_applied": sitl_pinned, "options": opts,
            "freezes": freezer.events if freezer else [], "probes": probed}  # fmt: skip


# -- the report -------------------------------------------------------------------------------


def analyse(run_dir: Path, record: dict[str, Any], hogs: int, mode: str,
            unix_minus_monotonic_s: float, lockstep_rmse_m: float | None = None,
            ) -> tuple[dict[str, Any], dict[str, Any]]:  # fmt: skip
    """(report, figure series) of a flown run."""
    opts: AttackOptions = record.get("options") or AttackOptions()
    flight = read_csv_columns(run_dir / "flight.csv")
    truth = read_csv_columns(run_dir / "groundtruth.csv")
    stats = json.loads((run_dir / "stats.json").read_text())
    unix_s, rates = analysis.attitude_sends((run_dir / "session.tlog").read_bytes(),
                                            SERVICE_SYSTEM_ID)  # fmt: skip
    att_t_s = unix_s - unix_minus_monotonic_s
    names = {int(p["pid"]): name for name, p in stats.get("processes", {}).items()
             if isinstance(p, dict) and p.get("pid") and name != "control"}  # fmt: skip
    period_s = 1.0 / 200.0
    samples = record["samples"]
    windows = [analysis.window_figures(w, flight, truth, att_t_s, rates, samples, names,
                                       period_s) for w in record["windows"]]  # fmt: skip
    steal = analysis.steal_figures(record.get("steal", {}), record["windows"], windows,
                                   flight, att_t_s, period_s, stats.get("stalls", []))  # fmt: skip
    (run_dir / "steal.json").write_text(json.dumps(record.get("steal", {})))
    attacks = [w for w in record["windows"] if w.attack]
    in_attack = np.zeros(flight["t_s"].size, dtype=bool)
    for w in attacks:
        in_attack |= (flight["t_s"] >= w.t0_s) & (flight["t_s"] <= w.t1_s)
    compute = flight["compute_us"][in_attack]
    rss = [s["control_rss_mb"] for s in samples
           if attacks and attacks[0].t0_s <= s["t_s"] <= attacks[-1].t1_s]  # fmt: skip
    counters = stats.get("counters", {})
    report = {
        "attitude_mode": mode, "hogs": hogs, "cpus": os.cpu_count(),
        "fifo_requested": record["fifo_priority"],
        "sitl_fifo": record["sitl_fifo"],
        "fifo_applied": counters.get("realtime_priority_refused", 0) == 0,
        "loops_cpu": record.get("loops_cpu"),
        "loops_cpu_applied": (record.get("loops_cpu") is not None
                              and counters.get("cpu_affinity_refused", 0) == 0),
        "sitl_cpu": record.get("sitl_cpu"),
        "sitl_cpu_applied": record.get("sitl_cpu_applied", False),
        "window_s": opts.attack_s, "zenoh_rate_per_s": ZENOH_RATE_PER_S,
        "fuzz_rate_hz": FUZZ_RATE_HZ, "autopilot": opts.autopilot, "signing": opts.signing,
        "forge": opts.forge, "attacks": list(opts.attacks),
        "freeze": {"helper": opts.freeze, "seconds": opts.freeze_s,
                   "events": record.get("freezes", [])} if opts.freeze else None,
        "load_avg": {k: [round(x, 2) for x in v] for k, v in record["load_avg"].items()},
        "service_exit": record["service_exit"],
        "windows": windows,
        "attack_compute_us": {"median": float(np.median(compute)),
                              "p99": float(np.percentile(compute, 99))},
        "control_rss": {
            "samples": len(rss), "start_mb": rss[0] if rss else None,
            "end_mb": rss[-1] if rss else None,
            "max_deviation": (max(rss, key=lambda r: abs(r - rss[0])) - rss[0]) / rss[0]
            if rss else None,
        },
        "stats_loops": stats.get("loops", {}),
        "stats_processes": stats.get("processes", {}),
        "stats_sharing": stats.get("sharing", {}),
        "stats_link": stats.get("link", {}),
        "stats_counters": counters,
        "stats_gc": stats.get("gc", {}),
        "stats_stalls": stats.get("stalls", []),
        "stats_misses": stats.get("misses", []),
        "stats_slow_steps": stats.get("slow_steps", {}),
        "stats_event_loop_steps": stats.get("event_loop_steps", {}),
        "steal": steal,
        # every position-loop gap over 12 ms and every deadline miss, with its verdict
        "attribution": analysis.attribution(record.get("steal", {}), record["windows"],
                                            stats.get("stalls", []), stats.get("misses", []),
                                            flight,
                                            stats.get("slow_steps", {}).get("steps", [])),
        "fuzz_datagrams_sent": fuzz_sent(record["windows"]),
        "link_refused": link_refused(stats.get("link", {})),
        "lockstep_rmse_m": lockstep_rmse_m,
        "figure8_rmse_m": analysis.figure8_rmse_m(windows),
        "floor_probe": floor_report(record.get("probes") or {}, flight, att_t_s,
                                    stats.get("misses", []), record["windows"], period_s),
    }  # fmt: skip
    err_t, err = analysis.error_series(flight, truth)
    series = {"pos_t_s": flight["t_s"][flight["phase"] == "offboard"], "att_t_s": att_t_s,
              "err_t_s": err_t, "err_m": err}  # fmt: skip
    for wake, meta in (record.get("probes") or {}).items():
        rec = floor_probe.read_records(Path(meta["path"]))
        series[f"probe_{wake}_t_s"] = rec["wake_s"]
        series[f"probe_{wake}_late_ms"] = 1e3 * (rec["wake_s"] - rec["due_s"])
    report["verdicts"] = [vars(v) for v in analysis.judge(report)]
    return report, series


def floor_report(probes: dict[str, Any], flight: dict[str, Any], att_t_s: Any,
                 misses: list[dict[str, Any]], wins: list[analysis.Window],
                 attitude_period_s: float) -> dict[str, Any] | None:  # fmt: skip
    """The machine's floor beside the loops (``analysis.floor_figures``), with how each
    probe ran (``Probes.close``: its wake, SCHED_FIFO applied, its compute); None with
    ``--no-probe``."""
    if not probes:
        return None
    records = {wake: floor_probe.read_records(Path(meta["path"]))
               for wake, meta in probes.items()}  # fmt: skip
    figures = analysis.floor_figures(records, flight, att_t_s, misses, wins, attitude_period_s)
    return {"probes": {w: {k: v for k, v in m.items() if k != "path"}
                       for w, m in probes.items()}, **figures}  # fmt: skip


# the link's counters that are not refusals (the rest each count a datagram or frame refused)
_LINK_NOT_REFUSED = frozenset({"datagrams", "received", "sent", "bad_data"})


def fuzz_sent(windows: list[analysis.Window]) -> int:
    """Datagrams the fuzzer sent over the flight (joint attacks' fuzz parts included)."""
    total = 0
    for w in windows:
        parts = w.attacker.get("parts", {"": w.attacker})
        total += sum(int(p.get("datagrams", 0)) for k, p in parts.items()
                     if "fuzz" in (k or w.kind).split("+"))  # fmt: skip
    return total


def link_refused(link: dict[str, Any]) -> dict[str, int]:
    """What the service's link refused, by reason, and in all (``total``): throttled
    sources, rejected headers, CRCs and signatures, other senders. Beside the fuzzer's
    datagrams: what of them reached no loop (the autopilot's unknown messages count too)."""
    out = {k: int(v) for k, v in sorted(link.items())
           if k not in _LINK_NOT_REFUSED and isinstance(v, int)}  # fmt: skip
    out["total"] = sum(out.values())
    return out


def lockstep_rmse_m() -> float | None:
    """The windy figure-8's RMSE flown in lockstep (``sim --scenario figure8 --lockstep``,
    body rates, the same SITL and service): what the real-time body-rate flight is judged
    against. None when that flight left no report."""
    with tempfile.TemporaryDirectory(prefix="epc-attack-lockstep-") as tmp:
        report = Path(tmp) / "report.json"
        subprocess.run(
            [sys.executable, "-m", "epc_offboard", "sim", "--scenario", "figure8", "--lockstep",
             "--gcs-port", "0", "--out", tmp, "--json", str(report)],
            capture_output=True, text=True, check=False, env=dict(os.environ, **service_env()),
        )  # fmt: skip
        if not report.exists():
            return None
        rmse: float = json.loads(report.read_text())["vehicles"][0]["tracking"]["rmse_m"]
        return rmse


def run_attack_bench(json_path: str | None, hogs: int, mode: str,
                     loops_cpu: int | None = None, sitl_cpu: int | None = None,
                     opts: AttackOptions | None = None) -> int:  # fmt: skip
    if hogs < 0:
        raise AttackBenchError("--hogs must be >= 0")
    out = Path(json_path) if json_path else None
    with tempfile.TemporaryDirectory(prefix="epc-attack-") as tmp:
        run_dir = out.with_suffix("") if out else Path(tmp)
        run_dir.mkdir(parents=True, exist_ok=True)
        for stale in ("flight.csv", "groundtruth.csv", "session.tlog", "stats.json",
                      "steal.json"):
            (run_dir / stale).unlink(missing_ok=True)
        unix_minus_monotonic_s = time.time() - time.monotonic()
        record = fly(run_dir, hogs, mode, loops_cpu, sitl_cpu, opts)
        lockstep = lockstep_rmse_m() if mode == "rates" else None
        report, series = analyse(run_dir, record, hogs, mode, unix_minus_monotonic_s,
                                 lockstep)  # fmt: skip
    print(analysis.format_table(report))
    if out:
        out.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
        fig = out.with_suffix(".png")
        analysis.write_figure(report, series, fig)
        print(f"report: {out}  figure: {fig}  flight files: {out.with_suffix('')}/")
    return 0
