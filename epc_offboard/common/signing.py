"""MAVLink 2 message signing: the key file, a signature check that verifies before it
records, and switching a pymavlink ``MAVLink`` object to signed traffic.

Shared by the service's link and the bundled SITL's endpoints (both sign and check alike).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import time
from pathlib import Path
from typing import Any

from epc_offboard.common.configio import ConfigError

log = logging.getLogger("epc_offboard.signing")


def load_signing_key(path: str | Path) -> bytes:
    """Read a MAVLink 2 signing key: exactly 32 raw bytes, or 64 hex characters."""
    data = Path(path).read_bytes()
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise ConfigError(f"{path}: signing key must be 32 raw bytes or 64 hex characters")


# Seconds between 1970-01-01 and the MAVLink signing epoch 2015-01-01.
SIGNING_EPOCH_UNIX_S = 1420070400
_SIGNATURE_LOG_PERIOD_S = 5.0
# A new stream may start at most this far behind our own signing clock (pymavlink's and
# MAVLink's rule: one minute, in the signature's 10 us units).
_NEW_STREAM_MAX_LAG = 60 * 100_000


class SignatureCheck:
    """MAVLink 2 signature check that verifies BEFORE it records: installed over pymavlink's.

    pymavlink's ``MAVLink.check_signature`` stores a frame's timestamp as its stream's newest
    before it checks the signature, so one wrong-key frame stamped "now" and claiming a
    genuine stream's (link id, system, component) makes every later genuine frame "old"
    for good. Here only a frame whose SHA-256 signature matches the key may move a stream's
    timestamp (or our own signing clock); the timestamp rules are otherwise MAVLink's: a
    known stream must move forward, a new one may start at most a minute behind our clock.

    ``rejected`` counts by reason (three fixed keys: bounded whatever the wire sends); the
    log line is rate-limited.
    """

    REASONS = ("bad_signature", "replayed", "stale_stream")

    def __init__(self, mav: Any) -> None:
        self._signing = mav.signing
        self.rejected: dict[str, int] = dict.fromkeys(self.REASONS, 0)
        self._last_log = -float("inf")

    def __call__(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        signing = self._signing
        # signature block: link id (1), timestamp (6, little-endian), signature (6)
        link_id = msgbuf[-13]
        timestamp = int.from_bytes(msgbuf[-12:-6], "little")
        digest = hashlib.sha256(bytes(signing.secret_key) + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            return self._reject("bad_signature", link_id, src_system, src_component)
        stream = (link_id, src_system, src_component)
        newest = signing.stream_timestamps.get(stream)
        if newest is not None and timestamp <= newest:
            return self._reject("replayed", link_id, src_system, src_component)
        if newest is None and timestamp + _NEW_STREAM_MAX_LAG < signing.timestamp:
            return self._reject("stale_stream", link_id, src_system, src_component)
        signing.stream_timestamps[stream] = timestamp
        signing.timestamp = max(signing.timestamp, timestamp)
        return True

    def _reject(self, reason: str, link_id: int, system: int, component: int) -> bool:
        self.rejected[reason] += 1
        now = time.monotonic()
        if now - self._last_log >= _SIGNATURE_LOG_PERIOD_S:
            self._last_log = now
            log.warning(
                "signed frame rejected (%s) claiming system %d component %d link %d; "
                "rejected so far: %s",
                reason, system, component, link_id,
                ", ".join(f"{k} {n}" for k, n in self.rejected.items()),
            )  # fmt: skip
        return False


def enable_signing(mav: Any, key: bytes, *, link_id: int = 0) -> SignatureCheck:
    """Sign what ``mav`` (a pymavlink ``MAVLink``) sends with ``key``, accept only frames
    signed with it, and check them with a :class:`SignatureCheck` (returned)."""
    check = SignatureCheck(mav)
    mav.signing.secret_key = key
    mav.signing.link_id = link_id
    # MAVLink signing timestamps count 10 us units since 2015-01-01.
    mav.signing.timestamp = int((time.time() - SIGNING_EPOCH_UNIX_S) * 1e5)
    mav.signing.sign_outgoing = True
    mav.signing.allow_unsigned_callback = lambda _mav, _msg_id: False
    mav.check_signature = check  # the instance's, over the class's: verify, then record
    return check
