"""A fleet through a Zenoh router, and trust (issue 25): real processes, real Zenoh on loopback.

The router is `epc-offboard fleet router` (a process), loaded with the config files shipped in
config/zenoh/ (the README points to them), with this test's certificates and password file
set by --cfg (vehicles: sharing.zenoh_overrides). Vehicles are FleetSharing sessions (their
fleet helper a process) in Zenoh client mode; attackers are plain Zenoh clients. A CA and its
certificates are made per test by trustme.

What a refusal looks like from each side: a vehicle refused by the router fails to open its
session (counted: session_open_failures) and flies alone; the router counts it (refused.*);
a publication the ACL denies never arrives (0 controllers accepted), and the router counts
each one (refused.acl_denied_put, from Zenoh's TRACE log of its access decisions: see
epc_offboard/fleet/router.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import trustme
import zenoh

from epc_offboard.common.children import launched_env
from epc_offboard.common.ports import free_port
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.fleet.sharing import FleetSharing, SharingConfig
from epc_offboard.fleet.wire import ControllerMessage, MessageKind, encode_controllers
from tests.test_sharing import TARGETS, controller, learn_new, until
from tests.test_sharing import peer as vehicle

pytestmark = pytest.mark.timeout(180)

REPO = Path(__file__).resolve().parents[1]
ZENOH_DIR = REPO / "config" / "zenoh"
FLEET = "fleet"  # the shipped ACLs' fleet
PASSWORDS = {"v1": "pw-one", "v2": "pw-two", "v3": "pw-three"}


class Pki:
    """A fleet CA, the router's certificate, one per vehicle (common name = its id), and a
    certificate for v1 from a CA nobody trusts."""

    def __init__(self, root: Path) -> None:
        root.mkdir(parents=True, exist_ok=True)
        self.root = root
        ca = trustme.CA()
        self.ca = root / "ca.pem"
        ca.cert_pem.write_to_path(str(self.ca))
        self.router_cert, self.router_key = self._leaf(
            ca.issue_cert("127.0.0.1", "localhost", common_name="router"), "router"
        )
        self.vehicle = {v: self._leaf(ca.issue_cert(v, common_name=v), v) for v in PASSWORDS}
        self.rogue = self._leaf(trustme.CA().issue_cert("v1", common_name="v1"), "rogue")
        self.passwords = root / "passwords"
        self.passwords.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))

    def _leaf(self, cert: trustme.LeafCert, name: str) -> tuple[Path, Path]:
        pem, key = self.root / f"{name}.pem", self.root / f"{name}-key.pem"
        cert.cert_chain_pems[0].write_to_path(str(pem))
        cert.private_key_pem.write_to_path(str(key))
        return pem, key


class Router:
    """`epc-offboard fleet router` in a process of its own; its JSON stats lines, read."""

    def __init__(self, proc: subprocess.Popen[str], endpoint: str, port: int) -> None:
        self.proc = proc
        self.endpoint = endpoint
        self.port = port
        self.lines: list[dict[str, Any]] = []
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.lines.append(json.loads(line))

    def stats(self) -> dict[str, Any]:
        stats = [s for s in self.lines if s["event"] in ("stats", "stopped")]
        return stats[-1] if stats else {}

    def refused(self, kind: str) -> int:
        return int(self.stats().get("refused", {}).get(kind, 0))


@contextlib.contextmanager
def router(
    tmp_path: Path, config: str, cfg: dict[str, Any], tls: bool, port: int = 0
) -> Iterator[Router]:
    port = port or free_port()
    endpoint = f"{'tls' if tls else 'tcp'}/127.0.0.1:{port}"
    args = [sys.executable, "-m", "epc_offboard", "fleet", "router", "--listen", endpoint,
            "--config", str(ZENOH_DIR / config), "--stats-every", "0.3"]  # fmt: skip
    for path, value in cfg.items():
        args += ["--cfg", f"{path}:{json.dumps(value)}"]
    log_path = tmp_path / f"router-{port}-{time.monotonic_ns()}.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=log, text=True, cwd=REPO,
                                env={**os.environ, **launched_env()})  # ends with pytest
    r = Router(proc, endpoint, port)
    try:
        deadline = time.monotonic() + 60
        while not any(s["event"] == "started" for s in r.lines):
            assert proc.poll() is None, log_path.read_text()
            assert time.monotonic() < deadline, "the router did not start"
            time.sleep(0.05)
        yield r
    finally:
        proc.send_signal(signal.SIGTERM)  # (a test may have stopped it already)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        r._thread.join(timeout=5)


def tls_router_cfg(pki: Pki) -> dict[str, Any]:
    return {
        "transport/link/tls/root_ca_certificate": str(pki.ca),
        "transport/link/tls/listen_certificate": str(pki.router_cert),
        "transport/link/tls/listen_private_key": str(pki.router_key),
    }


def vehicle_config(vid: str, r: Router, client_file: str, **overrides: Any) -> SharingConfig:
    return SharingConfig(
        enabled=True, fleet=FLEET, vehicle_id=vid, mode="client", connect=(r.endpoint,),
        zenoh_config_file=str(ZENOH_DIR / client_file) if client_file else "",
        zenoh_overrides=overrides, publish_period_s=0.05, query_timeout_s=2.0,
        candidates_per_s=5000.0, helper_nice=0,  # see tests/test_sharing.py's config()
    )  # fmt: skip


async def refused(cfg: SharingConfig) -> FleetSharing:
    """A vehicle whose session the router refuses: open fails (it would fly alone)."""
    sharing = FleetSharing(cfg, [("position", controller())])
    with pytest.raises(RuntimeError, match="did not open"):
        await sharing.open()
    sharing.close()
    assert sharing.stats()["session_open_failures"] == 1
    return sharing


def raw_client(r: Router, **cfg: Any) -> zenoh.Session:
    """Any Zenoh client (not ours): the attacker, or a tool reading the router's stats."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([r.endpoint]))
    for path, value in cfg.items():
        conf.insert_json5(path, json.dumps(value))
    return zenoh.open(conf)


def spoofed_batch(sig: str, as_vehicle: str, sets: list[tuple[int, ...]]) -> bytes:
    entries = tuple(LibraryEntry(s) for s in sets)
    return encode_controllers(ControllerMessage(MessageKind.BATCH, sig, as_vehicle, entries))


async def share_and_deny(
    r: Router, v1: FleetSharing, a: Any, b: Any, v2: FleetSharing, attacker: zenoh.Session
) -> None:
    """v1 -> v2 through the router; the attacker (authenticated as v3) publishes under v1's id
    (denied: nothing arrives) and then under its own (arrives: the path was open)."""
    s1 = learn_new(a, TARGETS[0])
    await until(lambda: s1 in b.candidates, "v1 -> v2 through the router")
    sig = a.problem.signature()
    forged = [(0, 1, 2), (3, 4)]
    received = v2.stats().get("messages_received", 0)
    denied = r.refused("acl_denied_put")
    for _ in range(5):
        attacker.put(f"epc/{FLEET}/{sig}/ctl/v1", spoofed_batch(sig, "v1", forged))
    # a declared publisher: its key expression's decision is cached (logged otherwise)
    forger = attacker.declare_publisher(f"epc/{FLEET}/{sig}/ctl/v2")
    for _ in range(4):
        forger.put(spoofed_batch(sig, "v2", forged))
    # sent after the forged ones, on the same session and route: once it is in, they would be
    attacker.put(f"epc/{FLEET}/{sig}/ctl/v3", spoofed_batch(sig, "v3", [(5, 6)]))
    await until(lambda: (5, 6) in b.candidates, "v3's own publication")
    assert all(s not in b.candidates for s in forged)  # 0 accepted from the denied sender
    assert v2.stats()["messages_received"] == received + 1  # v3's own only
    assert b.stats.received_shared == 0
    # every denied publication counted by the router, and nothing else taken for one
    await until(lambda: r.refused("acl_denied_put") >= denied + 9, "the router's count")
    await asyncio.sleep(1.0)  # (a count above 9 would show by now)
    assert r.refused("acl_denied_put") == denied + 9
    forger.undeclare()


def test_vehicles_share_through_a_plain_router_and_any_client_reads_its_stats(tmp_path):
    async def main() -> None:
        with router(tmp_path, "router.json5", {}, tls=False) as r:
            a, b = controller(), controller()
            async with (
                vehicle(vehicle_config("v1", r, "client.json5"), a),
                vehicle(vehicle_config("v2", r, "client.json5"), b),
            ):
                s1 = learn_new(a, TARGETS[0])
                await until(lambda: s1 in b.candidates, "v1 -> v2 through the router")
                await until(lambda: r.stats().get("sessions", {}).get("client", 0) == 2,
                            "the router's stats")  # fmt: skip
                zid = next(s["zid"] for s in r.lines if s["event"] == "started")
                with raw_client(r) as tool:
                    replies = list(tool.get(f"epc/router/{zid}/stats", timeout=5.0))
                    ok = [rep.ok for rep in replies if rep.ok is not None]
                    assert ok, "no stats reply"
                    stats = json.loads(ok[0].payload.to_string())
                    assert stats["sessions"]["client"] == 3  # v1, v2 and this tool
                    admin = [rep.ok for rep in tool.get(f"@/{zid}/router", timeout=5.0)
                             if rep.ok is not None]  # fmt: skip
                    assert admin, "Zenoh's admin space (adminspace.enabled)"
        final = r.stats()
        assert final["event"] == "stopped"
        assert final["transports_opened"] >= 3
        assert final["refused"] == {"tls_refused": 0, "auth_refused": 0}

    asyncio.run(main())


def test_tls_with_passwords_refuses_wrong_credentials_and_the_acl_denies_another_id(tmp_path):
    pki = Pki(tmp_path / "pki")
    cfg = {**tls_router_cfg(pki), "transport/auth/usrpwd/dictionary_file": str(pki.passwords)}

    def creds(vid: str, password: str) -> dict[str, Any]:
        return {"transport/link/tls/root_ca_certificate": str(pki.ca),
                "transport/auth/usrpwd/user": vid,
                "transport/auth/usrpwd/password": password}  # fmt: skip

    async def main() -> None:
        with router(tmp_path, "router-tls.json5", cfg, tls=True) as r:
            # refused: a wrong password, an unknown user, no credentials at all
            no_creds = {"transport/link/tls/root_ca_certificate": str(pki.ca)}
            for base, bad in (("client-tls.json5", creds("v2", "wrong")),
                              ("client-tls.json5", creds("intruder", "pw-two")),
                              ("client.json5", no_creds)):  # fmt: skip
                await refused(vehicle_config("v2", r, base, **bad))
            await until(lambda: r.refused("auth_refused") >= 3, "the router counting them")
            a, b = controller(), controller()
            async with (
                vehicle(vehicle_config("v1", r, "client-tls.json5", **creds("v1", "pw-one")),
                        a) as v1,
                vehicle(vehicle_config("v2", r, "client-tls.json5", **creds("v2", "pw-two")),
                        b) as v2,
            ):  # fmt: skip
                with raw_client(r, **creds("v3", "pw-three")) as attacker:
                    await share_and_deny(r, v1, a, b, v2, attacker)
            assert r.refused("tls_refused") == 0

    asyncio.run(main())


def test_mutual_tls_refuses_a_vehicle_without_a_trusted_certificate_and_the_acl_holds(tmp_path):
    pki = Pki(tmp_path / "pki")

    def cert(pem_key: tuple[Path, Path]) -> dict[str, Any]:
        return {"transport/link/tls/root_ca_certificate": str(pki.ca),
                "transport/link/tls/connect_certificate": str(pem_key[0]),
                "transport/link/tls/connect_private_key": str(pem_key[1])}  # fmt: skip

    async def main() -> None:
        with router(tmp_path, "router-mtls.json5", tls_router_cfg(pki), tls=True) as r:
            # no certificate (TLS only: it checks the router, shows nothing), a rogue CA's
            no_cert = {"transport/link/tls/root_ca_certificate": str(pki.ca)}
            await refused(vehicle_config("v1", r, "client.json5", **no_cert))
            await refused(vehicle_config("v1", r, "client-mtls.json5", **cert(pki.rogue)))
            await until(lambda: r.refused("tls_refused") >= 2, "the router counting them")
            a, b = controller(), controller()
            async with (
                vehicle(vehicle_config("v1", r, "client-mtls.json5", **cert(pki.vehicle["v1"])),
                        a) as v1,
                vehicle(vehicle_config("v2", r, "client-mtls.json5", **cert(pki.vehicle["v2"])),
                        b) as v2,
            ):  # fmt: skip
                attacker_cfg = {**cert(pki.vehicle["v3"]), "transport/link/tls/enable_mtls": True}
                with raw_client(r, **attacker_cfg) as attacker:
                    await share_and_deny(r, v1, a, b, v2, attacker)

    asyncio.run(main())


def test_zenoh_overrides_unknown_keys_are_config_errors():
    with pytest.raises(ValueError, match=r"zenoh_overrides\.transport/link/tls/nope"):
        SharingConfig(zenoh_overrides={"transport/link/tls/nope": True})
    with pytest.raises(ValueError, match="client does not listen"):
        SharingConfig(mode="client", listen=("tcp/127.0.0.1:7447",))



def test_vehicles_rejoin_a_restarted_router_and_catch_up(tmp_path):
    """A router that restarts (same endpoint) is rejoined by its clients; what a vehicle
    learned while it was down reaches the others (the library query on a peer's return)."""

    async def main() -> None:
        a, b = controller(), controller()
        with router(tmp_path, "router.json5", {}, tls=False) as r:
            async with (
                vehicle(vehicle_config("v1", r, "client.json5"), a),
                vehicle(vehicle_config("v2", r, "client.json5"), b),
            ):
                s1 = learn_new(a, TARGETS[0])
                await until(lambda: s1 in b.candidates, "v1 -> v2")
                r.proc.send_signal(signal.SIGTERM)
                r.proc.wait(timeout=10)
                s2 = learn_new(a, TARGETS[1])  # published into a fleet with no router
                await asyncio.sleep(0.5)
                with router(tmp_path, "router.json5", {}, tls=False, port=r.port) as r2:
                    await until(lambda: s2 in b.candidates, "v1 -> v2 after the restart", 60)
                    await until(lambda: r2.stats().get("sessions", {}).get("client", 0) == 2,
                                "both clients in the restarted router's stats")  # fmt: skip

    asyncio.run(main())


@pytest.mark.slow
def test_the_fleet_bench_runs_three_vehicles_through_a_router(tmp_path):
    """`bench --fleet`'s shape and its bookkeeping: every pair's controller arrives, every
    vehicle discovers the others (figures are the bench's, not asserted here)."""
    from epc_offboard.cli import main

    out = tmp_path / "fleet.json"
    assert main(["bench", "--fleet", "--vehicles", "3", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["sessions_failed"] == 0
    assert report["discovered"] == 3
    assert report["propagation_s"]["received"] == report["propagation_s"]["pairs"] == 6
    assert 0 < report["propagation_s"]["p50"] <= report["propagation_s"]["max"]
    assert report["router"]["event"] == "stopped"
    wire = report["bytes_per_vehicle_s"]["wire"]  # every vehicle's connection, both ways
    assert wire["connections"] == 3
    assert 0 < wire["down_p50"] <= wire["down_max"]
    assert 0 < wire["up_p50"] <= wire["up_max"]
    assert report["bytes_per_vehicle_s"]["payload"]["bytes_published"] > 0
    assert (tmp_path / "fleet.png").stat().st_size > 0  # the figure beside it
