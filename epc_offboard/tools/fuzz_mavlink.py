"""A MAVLink fuzzer: mixed garbage datagrams to a UDP port at a fixed rate (issue 21's attack).

``python -m epc_offboard.tools.fuzz_mavlink --port P [--rate 2000] [--duration 10]``

Each datagram is one of (equal shares, from a seeded generator):

* ``random``: random bytes, 1..300 long (not MAVLink at all);
* ``magic``: MAVLink 2's magic byte and a plausible header, then random bytes (bad CRC);
* ``mavlink1``: a well-formed MAVLink 1 frame of the vehicle's ids;
* ``wrong_id``: a frame with a valid CRC, the vehicle's system and component, and a message
  id the service does not read (or none of the dialect's);
* ``other_system``: well-formed state and heartbeats from other system ids;
* ``nan``: well-formed state from the vehicle's own ids, with NaN and infinite fields;
* ``time_jump``: well-formed, plausible state from the vehicle's own ids stamped at random
  times (far ahead of or behind the vehicle's clock).

With ``--forge``, also ``forged``: a coherent forged stream from the vehicle's own ids (its
own timeline, starting a little ahead of the vehicle's, advancing in real time, the vehicle
placed 10 m away) and heartbeats claiming another mode. On an unsigned link nothing in a
frame tells it from the vehicle's; only its contradiction with the vehicle's own stream can
(the state tracker's innovation gate). Also ``wrong_key``: the same forged stream signed
with a key of the fuzzer's own (timestamps at the signing clock's now): on a signed link
the signature rejects it, and a check that recorded a timestamp before verifying it would
lock the genuine stream out. Off by default.

Prints a JSON summary (datagrams sent by kind, the achieved rate) on exit.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import socket
import struct
import sys
import time
from collections import Counter
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

# The ids a service reads (written out here, not imported: the attack must not depend on the
# defence, and runs against older versions of the service too).
_READ_IDS = frozenset({0, 2, 22, 30, 31, 32, 33, 77, 111, 245, 253, 331})
_UNUSED_IDS = sorted(set(mavlink.mavlink_map) - _READ_IDS)


class Fuzzer:
    """Makes one datagram at a time; ``kinds`` chooses the mix (see the module docstring)."""

    KINDS = ("random", "magic", "mavlink1", "wrong_id", "other_system", "nan", "time_jump")

    def __init__(
        self, seed: int = 0, *, system_id: int = 1, component_id: int = 1, forge: bool = False
    ) -> None:
        self.rng = random.Random(seed)
        self.own = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._system_id = system_id
        self.kinds = self.KINDS + (("forged", "wrong_key") if forge else ())
        self._make: dict[str, Callable[[], bytes]] = {
            "random": self._random,
            "magic": self._magic,
            "mavlink1": self._mavlink1,
            "wrong_id": self._wrong_id,
            "other_system": self._other_system,
            "nan": self._nan,
            "time_jump": self._time_jump,
            "forged": self._forged,
            "wrong_key": self._wrong_key,
        }
        self.signed = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        if forge:
            # MAVLink's signing clock: 10 us units since 2015-01-01, stamped "now"
            now = int((time.time() - 1420070400) * 100_000)
            self.signed.signing.secret_key = bytearray(self.rng.randbytes(32))
            self.signed.signing.link_id = 0
            self.signed.signing.timestamp = now
            self.signed.signing.sign_outgoing = True
        self._forge_t0 = time.monotonic()
        self._forge_boot_ms = 0

    def datagram(self) -> tuple[str, bytes]:
        kind = self.rng.choice(self.kinds)
        return kind, self._make[kind]()

    def _random(self) -> bytes:
        return self.rng.randbytes(self.rng.randint(1, 300))

    def _magic(self) -> bytes:
        plen = self.rng.randint(0, 255)
        header = bytes([0xFD, plen, 0, 0, self.rng.randint(0, 255), self._system_id, 1])
        msg_id = self.rng.choice((30, 31, 32, 331, 0, self.rng.randint(0, 2**24 - 1)))
        return header + msg_id.to_bytes(3, "little") + self.rng.randbytes(plen + 2)

    def _mavlink1(self) -> bytes:
        msg = self.own.attitude_encode(self.rng.randint(0, 2**32 - 1), 0.0, 0.0, 0.0, 0, 0, 0)
        return bytes(msg.pack(self.own, force_mavlink1=True))

    def _wrong_id(self) -> bytes:
        rng = self.rng
        if rng.random() < 0.5:
            msg_id = rng.choice(_UNUSED_IDS)
            crc_extra = mavlink.mavlink_map[msg_id].crc_extra
            plen = rng.randint(1, mavlink.mavlink_map[msg_id].unpacker.size)
        else:
            msg_id = rng.randint(20_000, 2**24 - 1)  # in no dialect
            crc_extra, plen = rng.randint(0, 255), rng.randint(1, 255)
        header = struct.pack(
            "<BBBBBBBHB", 0xFD, plen, 0, 0, rng.randint(0, 255), self._system_id, 1,
            msg_id & 0xFFFF, msg_id >> 16,
        )  # fmt: skip
        body = rng.randbytes(plen)
        crc = mavlink.x25crc(header[1:] + body + bytes([crc_extra])).crc
        return header + body + struct.pack("<H", crc)

    def _state(self, mav: mavlink.MAVLink, t_ms: int, values: list[float]) -> bytes:
        kind = self.rng.randrange(3)
        if kind == 0:
            return bytes(mav.attitude_encode(t_ms, *values[:6]).pack(mav))
        if kind == 1:
            return bytes(mav.local_position_ned_encode(t_ms, *values[:6]).pack(mav))
        q = values[:4]
        return bytes(mav.attitude_quaternion_encode(t_ms, *q, *values[4:7]).pack(mav))

    def _other_system(self) -> bytes:
        mav = mavlink.MAVLink(
            None, srcSystem=self.rng.choice([s for s in range(1, 256) if s != self._system_id]),
            srcComponent=1,
        )  # fmt: skip
        if self.rng.random() < 0.2:
            return bytes(mav.heartbeat_encode(2, 12, 129, 4 << 16 | 3 << 24, 4).pack(mav))
        values = [self.rng.uniform(-20.0, 20.0) for _ in range(7)]
        return self._state(mav, self.rng.randint(0, 2**32 - 1), values)

    def _nan(self) -> bytes:
        bad = (math.nan, math.inf, -math.inf)
        values = [0.0] * 7
        for i in self.rng.sample(range(7), self.rng.randint(1, 3)):
            values[i] = self.rng.choice(bad)
        values[0] = values[0] if not math.isfinite(values[0]) else 1.0
        return self._state(self.own, self.rng.randint(0, 2**32 - 1), values)

    def _time_jump(self) -> bytes:
        # a hover-like, plausible sample; only its stamp is wrong
        values = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        if self.rng.random() < 0.5:
            values = [0.0, 0.0, -2.5, 0.0, 0.0, 0.0, 0.0]
        return self._state(self.own, self.rng.randint(0, 2**32 - 1), values)

    def _forged(self) -> bytes:
        mav = self.own
        t_ms = 600_000 + int((time.monotonic() - self._forge_t0) * 1000)
        if self.rng.random() < 0.1:
            return bytes(mav.heartbeat_encode(2, 12, 129, 4 << 16 | 3 << 24, 4).pack(mav))
        if self.rng.random() < 0.5:
            return bytes(mav.attitude_quaternion_encode(t_ms, 1, 0, 0, 0, 0, 0, 0).pack(mav))
        return bytes(mav.local_position_ned_encode(t_ms, 10.0, 0.0, -2.5, 0, 0, 0).pack(mav))

    def _wrong_key(self) -> bytes:
        """The forged stream, signed with the fuzzer's own key (pymavlink signs it)."""
        mav = self.signed
        t_ms = 600_000 + int((time.monotonic() - self._forge_t0) * 1000)
        if self.rng.random() < 0.5:
            return bytes(mav.attitude_quaternion_encode(t_ms, 1, 0, 0, 0, 0, 0, 0).pack(mav))
        return bytes(mav.local_position_ned_encode(t_ms, 10.0, 0.0, -2.5, 0, 0, 0).pack(mav))


def run(
    port: int, rate_hz: float, duration_s: float, seed: int, *, host: str, forge: bool
) -> dict[str, object]:
    fuzzer = Fuzzer(seed, forge=forge)
    sent: Counter[str] = Counter()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setblocking(False)
        t0 = time.monotonic()
        n = 0
        while (now := time.monotonic()) - t0 < duration_s:
            due = int((now - t0) * rate_hz) + 1
            while n < due:  # catch up after a late wake-up: the rate is the rate
                kind, data = fuzzer.datagram()
                try:
                    sock.sendto(data, (host, port))
                    sent[kind] += 1
                except (BlockingIOError, OSError):
                    sent["send_failed"] += 1
                n += 1
            time.sleep(max(0.0, t0 + n / rate_hz - time.monotonic()))
        elapsed = time.monotonic() - t0
    total = sum(v for k, v in sent.items() if k != "send_failed")
    return {
        "sent": dict(sent),
        "datagrams": total,
        "duration_s": elapsed,
        "rate_hz": total / elapsed,
        "start_monotonic_s": t0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--port", type=int, required=True, help="the service's UDP port")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--rate", type=float, default=2000.0, help="datagrams per second")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--forge", action="store_true", help="also forge the vehicle's state")
    args = parser.parse_args(argv)
    if args.port in (14540, 14550) and args.duration > 1.0:
        parser.error("not at the autopilot's ports 14540/14550 for more than a second")
    summary = run(args.port, args.rate, args.duration, args.seed, host=args.host, forge=args.forge)
    json.dump(summary, sys.stdout)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
