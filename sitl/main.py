"""``epc-sitl``: one simulated quadrotor speaking MAVLink 2 over UDP like a PX4 SITL instance.

Exit codes: 0 on success (also on SIGINT/SIGTERM), 2 on bad usage or an invalid config,
1 on a runtime failure.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import sys
from pathlib import Path
from typing import Any

from epc_offboard.common.children import die_with_launcher
from epc_offboard.common.cliargs import (
    MAX_PORT,
    WIND_PROFILE_HELP,
    bounded_int,
    check_port_free,
    join_negative_values,
    parse_wind,
    parse_wind_profile,
    port_number,
    positive_number,
)
from epc_offboard.common.configio import ConfigError
from epc_offboard.common.errors import UsageError
from sitl.endpoint import Counters, SitlEndpoint
from sitl.groundtruth import GroundTruthWriter
from sitl.lockstep import Clock, LockstepGate
from sitl.params import AUTOPILOTS, DEFAULT_VEHICLE_FILE, load_sim_config
from sitl.simulation import Simulation
from sitl.tcp import GcsTcpServer

HOST = "127.0.0.1"


MAX_INSTANCE = 254  # system id I + 1 is a MAVLink byte (1-255)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="epc-sitl",
        description="Simulated quadrotor speaking MAVLink 2 like a PX4 (default) or an "
        "ArduCopter SITL instance.",
    )
    arg = ap.add_argument
    arg(
        "--instance", type=bounded_int(0, MAX_INSTANCE), default=0, metavar="I",
        help="system id I+1, ports +I",
    )  # fmt: skip
    arg("--lockstep", action="store_true", help="advance only when the controller answered")
    arg(
        "--autopilot",
        choices=sorted(AUTOPILOTS),
        help="the autopilot personality (default: sitl.autopilot of the config, px4)",
    )
    arg("--wind", type=parse_wind, metavar="SPEED_M_S,DIR_DEG", help="towards, CCW from east")
    arg("--wind-profile", type=parse_wind_profile, metavar="SPEC", help=WIND_PROFILE_HELP)
    arg("--seed", type=bounded_int(0), default=0, metavar="S", help="seeds gusts and noise")
    arg("--config", type=Path, default=DEFAULT_VEHICLE_FILE, metavar="FILE", help="vehicle TOML")
    arg("--groundtruth", type=Path, metavar="FILE", help="write the true state to this CSV")
    arg("--signing-key", type=Path, metavar="FILE", help="file holding a 32-byte MAVLink key")
    arg("--speedup", type=positive_number, default=1.0, metavar="X",
        help="pace = wall clock x this")  # fmt: skip
    arg("--listen-port", type=port_number, metavar="P", help="default 14580+I; 0 = any free")
    arg("--offboard-port", type=port_number, metavar="P", help="telemetry to 127.0.0.1:P, 14540+I")
    arg(
        "--gcs-port",
        type=port_number,
        metavar="P",
        help="ground station, 0 = off: px4 sends to udp 14550; ardupilot listens on tcp "
        "5760+10*I, as ArduPilot SITL",
    )
    arg(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set an autopilot parameter at start (ardupilot: GUID_OPTIONS, GUID_TIMEOUT, "
        "ATC_INPUT_TC), as ArduPilot SITL's --defaults; repeatable",
    )
    arg("--lockstep-period-ms", type=positive_number, metavar="MS", help="sitl.lockstep_period_s")
    arg("--lockstep-timeout-ms", type=positive_number, metavar="MS",
        help="sitl.lockstep_timeout_s")  # fmt: skip
    arg("--duration", type=positive_number, metavar="S",
        help="exit after S seconds of vehicle time")  # fmt: skip
    arg(
        "--realtime-priority", type=bounded_int(0, 99), default=0, metavar="P",
        help="run SCHED_FIFO at P (1..99, where permitted: a refusal is said and counted, "
        "and it runs on), as an autopilot on hardware of its own; 0: normal scheduling",
    )  # fmt: skip
    return ap


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    sitl: dict[str, Any] = {}
    environment: dict[str, Any] = {}
    if args.wind is not None:
        environment.update(wind_speed_m_s=args.wind[0], wind_dir_deg=args.wind[1])
    if args.wind_profile is not None:
        environment.update(args.wind_profile.environment())
    if environment:
        out["environment"] = environment
    if args.autopilot is not None:
        sitl["autopilot"] = args.autopilot
    if args.lockstep_period_ms is not None:
        sitl["lockstep_period_s"] = args.lockstep_period_ms / 1000.0
    if args.lockstep_timeout_ms is not None:
        sitl["lockstep_timeout_s"] = args.lockstep_timeout_ms / 1000.0
    if sitl:
        out["sitl"] = sitl
    return out


def link_addresses(args: argparse.Namespace) -> tuple[int, list[tuple[str, int]]]:
    """PX4 SITL port plan: listen on 14580+I, telemetry to 14540+I and the GCS port (0 = off).
    The ardupilot personality keeps the UDP offboard link (as ``--serial1 udpclient:...``
    gives ArduPilot SITL one) and serves its ground station on TCP (:func:`gcs_tcp_port`)."""
    listen_port = 14580 + args.instance if args.listen_port is None else args.listen_port
    offboard_port = 14540 + args.instance if args.offboard_port is None else args.offboard_port
    gcs_udp = 0 if _personality(args) == "ardupilot" else args.gcs_port
    gcs_udp = 14550 if gcs_udp is None else gcs_udp
    return listen_port, [(HOST, p) for p in (offboard_port, gcs_udp) if p]


def gcs_tcp_port(args: argparse.Namespace) -> int:
    """ArduPilot SITL's ground-station port: TCP 5760 + 10 * instance (0: none)."""
    if _personality(args) != "ardupilot":
        return 0
    return 5760 + 10 * int(args.instance) if args.gcs_port is None else int(args.gcs_port)


def _personality(args: argparse.Namespace) -> str:
    return str(getattr(args, "personality", None) or args.autopilot or "px4")


def _check_ports(args: argparse.Namespace, listen_port: int) -> None:
    """The ports this instance binds: a port number out of range (14580 + I, 5760 + 10 I) or
    a taken one is said now, naming it, before the simulation starts."""
    tcp_port = gcs_tcp_port(args)
    for kind, port, flag in (("udp", listen_port, "--listen-port"),
                             ("tcp", tcp_port, "--gcs-port")):  # fmt: skip
        if port > MAX_PORT:
            raise UsageError(f"{flag}: --instance {args.instance} puts it at {port} > {MAX_PORT}")
        check_port_free(kind, HOST, port, f"{flag} (instance {args.instance})")


def _params(text: list[str]) -> list[tuple[str, float]]:
    out = []
    for item in text:
        name, sep, value = item.partition("=")
        try:
            out.append((name.strip().upper(), float(value)))
        except ValueError:
            sep = ""
        if not sep or not name.strip():
            raise UsageError(f"--param wants NAME=VALUE, got {item!r}")
    return out


def _signing_key(path: Path | None) -> bytes | None:
    if path is None:
        return None
    try:
        key = path.read_bytes()
    except OSError as exc:
        raise UsageError(f"--signing-key: cannot read {path}: {exc}") from exc
    if len(key) != 32:
        raise UsageError(f"--signing-key: {path} must hold exactly 32 bytes, has {len(key)}")
    return key


def _realtime(priority: int, counters: Counters) -> None:
    """This process SCHED_FIFO at ``priority`` (threads started later inherit it); refused
    (no CAP_SYS_NICE): said, counted (``realtime_priority_refused``), and the SITL runs on."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        counters.realtime_priority_refused += 1
        print(f"epc-sitl: SCHED_FIFO {priority} refused ({exc}): normal scheduling",
              file=sys.stderr, flush=True)  # fmt: skip


async def run(args: argparse.Namespace) -> Counters:
    config = load_sim_config(args.config, _overrides(args))
    args.personality = config.sitl.autopilot
    key = _signing_key(args.signing_key)
    sysid = args.instance + 1
    listen_port, dests = link_addresses(args)
    _check_ports(args, listen_port)

    sim = Simulation(config, seed=args.seed)
    for name, value in _params(args.param):
        if not sim.autopilot.set_parameter(name, value):
            raise UsageError(
                f"--param {name}={value:g}: not a parameter the {config.sitl.autopilot} "
                "personality lets you set"
            )
    counters = Counters()
    if args.realtime_priority:
        _realtime(args.realtime_priority, counters)
    gate = LockstepGate(
        args.lockstep,
        config.sitl.lockstep_timeout_s,
        config.sitl.lockstep_max_timeouts,
        config.sitl.lockstep_left_max_timeouts,
    )
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    with contextlib.ExitStack() as resources:
        writer = None
        if args.groundtruth is not None:
            writer = GroundTruthWriter(args.groundtruth, config.sitl.groundtruth_flush_s)
            resources.callback(writer.close)
        transport, endpoint = await loop.create_datagram_endpoint(
            lambda: SitlEndpoint(
                sim, sysid, dests, counters, key, gate.on_answer, gate.on_offboard
            ),
            local_addr=(HOST, listen_port),
        )
        resources.callback(transport.close)
        tcp_port = gcs_tcp_port(args)
        gcs_tcp = None
        if tcp_port:
            gcs_tcp = GcsTcpServer(endpoint, key)
            tcp_port = await gcs_tcp.start(HOST, tcp_port)
            resources.callback(gcs_tcp.close)

        def tick() -> None:
            sim.advance_tick()
            endpoint.emit()
            if writer is not None:
                writer.write(sim)

        port = transport.get_extra_info("sockname")[1]
        print(
            f"epc-sitl: instance {args.instance}, sysid {sysid}, listening udp {HOST}:{port}, "
            f"telemetry -> {', '.join(f'{h}:{p}' for h, p in dests) or 'none'}"
            + (f", ground station tcp {HOST}:{tcp_port}" if gcs_tcp is not None else "")
            + f", autopilot {config.sitl.autopilot}",
            flush=True,
        )
        clock = Clock(
            gate,
            config.sitl.lockstep_period_s,
            args.speedup,
            answer_due_ms=lambda: endpoint.newest_state_stamp_ms,
            announce=endpoint.announce,
        )
        sim.since_tick_us = clock.since_tick_us
        sim.setpoints_between_ticks = not args.lockstep
        await clock.run(tick, stop, args.duration)
    counters.lockstep_timeouts = gate.timeouts
    counters.lockstep_fallbacks = gate.fallbacks
    counters.offboard_failsafes = sim.autopilot.failsafe_count
    counters.rtl_entered = sim.autopilot.rtl_count
    return counters


def main(argv: list[str] | None = None) -> int:
    die_with_launcher()
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(join_negative_values(argv, ("--wind",)))
    try:
        counters = asyncio.run(run(args))
    except (ConfigError, UsageError) as exc:
        print(f"epc-sitl: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"epc-sitl: {exc}", file=sys.stderr)
        return 1
    print(f"epc-sitl: counters {counters.summary()}", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
