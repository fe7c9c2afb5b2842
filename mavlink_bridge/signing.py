"""MAVLink 2 message signing (https://mavlink.io/en/guide/message_signing.html).

A signed MAVLink 2 packet has the ``MAVLINK_IFLAG_SIGNED`` (0x01) incompat flag and a
13-byte block after the CRC: ``link_id`` (1 byte), ``timestamp`` (6 bytes, little
endian, units of 10 us since 2015-01-01 00:00:00 UTC) and ``signature`` (6 bytes)
= the first 48 bits of ``SHA-256(secret_key + header + payload + CRC + link_id +
timestamp)``.

Signing of outgoing packets is pymavlink's own (``MAVLink.signing``); incoming
signatures are verified here rather than by pymavlink, because pymavlink's
``check_signature`` records a stream's timestamp *before* checking the signature: a
forged packet with a far-future timestamp would make every later genuine packet of that
stream look like a replay. ``SignatureVerifier`` only advances a stream's timestamp on a
valid signature.

Key file (``load_signing_key``): exactly 64 hexadecimal characters (the 32-byte secret;
surrounding whitespace and one trailing newline are allowed), owner-only permissions
(no group/other bits, e.g. ``chmod 600``). ``write_signing_key`` (or ``python -m mavlink_bridge.keytool --generate FILE``) creates one.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

from .errors import BridgeError

__all__ = [
    "KEY_LEN",
    "SIGNATURE_BLOCK_LEN",
    "IFLAG_SIGNED",
    "SigningKeyError",
    "SigningConfig",
    "SignatureVerifier",
    "SIG_UNSIGNED",
    "SIG_VALID",
    "SIG_BAD",
    "SIG_REPLAY",
    "SIG_UNCHECKED",
    "load_signing_key",
    "write_signing_key",
    "signing_timestamp_now",
]

KEY_LEN = 32
"""Secret key length, bytes."""
SIGNATURE_BLOCK_LEN = 13
"""link_id (1) + timestamp (6) + signature (6)."""
IFLAG_SIGNED = 0x01
"""MAVLINK_IFLAG_SIGNED: incompat flag of a signed MAVLink 2 packet."""
EPOCH_2015_UNIX_S = 1_420_070_400
"""2015-01-01 00:00:00 UTC as a UNIX time: the signing timestamp's epoch."""
TIMESTAMP_UNITS_PER_S = 100_000
"""Signing timestamps count 10 us units."""
NEW_STREAM_MAX_AGE_S = 60.0
"""A new (link_id, system, component) stream is accepted only if its timestamp is at most
one minute behind the local clock (the spec's rule against replaying old captures)."""

# Status of a received packet's signature (``Received.signature``).
SIG_UNSIGNED = "unsigned"
"""No signature block (MAVLink 1, or MAVLink 2 without the signed flag)."""
SIG_VALID = "valid"
"""Signature verified with our key, timestamp newer than the stream's last one."""
SIG_BAD = "bad signature"
"""Signed, but not with our key (or the packet was altered)."""
SIG_REPLAY = "replayed timestamp"
"""Correctly signed, but its timestamp is not newer than the stream's last (a replay) or
a new stream's timestamp is more than a minute old."""
SIG_UNCHECKED = "unchecked"
"""Signed, but this endpoint has no key to check it with."""


class SigningKeyError(BridgeError, ValueError):
    """The signing key file is missing, readable by others, or not a 32-byte key."""


def load_signing_key(path: str | os.PathLike) -> bytes:
    """Read the 32-byte MAVLink signing key from ``path`` (64 hex characters, owner-only
    permissions). Raises SigningKeyError naming the file and the fix."""
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise SigningKeyError(
            f"MAVLink signing key file {p} does not exist; create one with "
            f"`python -m mavlink_bridge.keytool --generate {p}` (64 hex characters, mode 600)"
        ) from None
    except OSError as exc:
        raise SigningKeyError(f"cannot read MAVLink signing key file {p}: {exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise SigningKeyError(f"MAVLink signing key file {p} is not a regular file")
    loose = stat.S_IMODE(st.st_mode) & 0o077
    if loose:
        raise SigningKeyError(
            f"MAVLink signing key file {p} is accessible by group/others (mode {stat.S_IMODE(st.st_mode):#o}); "
            f"fix it with: chmod 600 {p}"
        )
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise SigningKeyError(f"cannot read MAVLink signing key file {p}: {exc}") from None
    try:
        hex_text = text.decode("ascii").strip()
        key = bytes.fromhex(hex_text)
        if len(hex_text) != 2 * KEY_LEN:
            raise ValueError
    except (UnicodeDecodeError, ValueError):
        raise SigningKeyError(
            f"MAVLink signing key file {p} must hold exactly {2 * KEY_LEN} hexadecimal characters "
            f"(a {KEY_LEN}-byte key), got {len(text)} bytes that are not"
        ) from None
    return key


def write_signing_key(path: str | os.PathLike, key: bytes | None = None) -> bytes:
    """Create ``path`` (mode 600, must not exist) holding ``key`` (default: 32 random bytes)
    as 64 hex characters and a newline. Returns the key."""
    key = secrets.token_bytes(KEY_LEN) if key is None else bytes(key)
    if len(key) != KEY_LEN:
        raise SigningKeyError(f"a MAVLink signing key has {KEY_LEN} bytes, got {len(key)}")
    fd = os.open(os.fspath(path), os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    return key


def signing_timestamp_now(unix_time_s: float | None = None) -> int:
    """The signing timestamp for ``unix_time_s`` (default now): 10 us units since 2015."""
    t = time.time() if unix_time_s is None else unix_time_s
    return max(0, int((t - EPOCH_2015_UNIX_S) * TIMESTAMP_UNITS_PER_S))


@dataclass(frozen=True)
class SigningConfig:
    """Signing of one endpoint: the shared secret and the link id stamped on what it sends."""

    key: bytes = field(repr=False)
    link_id: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.key, (bytes, bytearray)) or len(self.key) != KEY_LEN:
            raise SigningKeyError(f"a MAVLink signing key has {KEY_LEN} bytes, got {len(self.key) if hasattr(self.key, '__len__') else self.key!r}")
        if not (0 <= self.link_id <= 255):
            raise ValueError(f"signing link_id must be 0..255, got {self.link_id}")


class SignatureVerifier:
    """Checks the signature block of received MAVLink 2 packets against one key, with the
    spec's replay protection per (link_id, system, component) stream. Not thread-safe."""

    def __init__(self, key: bytes, clock=time.time) -> None:
        if len(key) != KEY_LEN:
            raise SigningKeyError(f"a MAVLink signing key has {KEY_LEN} bytes, got {len(key)}")
        self._key = bytes(key)
        self._clock = clock
        self._streams: dict[tuple[int, int, int], int] = {}

    def verify(self, packet: bytes, src_system: int, src_component: int) -> str:
        """One of SIG_UNSIGNED, SIG_VALID, SIG_BAD, SIG_REPLAY for a whole packet."""
        if len(packet) < 10 + 2 + SIGNATURE_BLOCK_LEN or packet[0] != 0xFD or not packet[2] & IFLAG_SIGNED:
            return SIG_UNSIGNED
        expected = hashlib.sha256(self._key + packet[:-6]).digest()[:6]
        if not hmac.compare_digest(expected, packet[-6:]):
            return SIG_BAD
        link_id = packet[-13]
        timestamp = int.from_bytes(packet[-12:-6], "little")
        stream = (link_id, src_system, src_component)
        last = self._streams.get(stream)
        if last is None:
            if timestamp < signing_timestamp_now(self._clock()) - NEW_STREAM_MAX_AGE_S * TIMESTAMP_UNITS_PER_S:
                return SIG_REPLAY
        elif timestamp <= last:
            return SIG_REPLAY
        self._streams[stream] = timestamp
        return SIG_VALID
