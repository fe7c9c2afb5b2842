"""Frame-level MAVLink tools for tests and fuzzers (issue 10): build, split and re-CRC raw
MAVLink 1/2 frames so that a fuzzer can send packets with a valid CRC but wrong fields,
without importing pymavlink itself (this package is the project's only pymavlink import).

Wire layout (https://mavlink.io/en/guide/serialization.html):
  v2: 0xFD len incompat compat seq sysid compid msgid(3, LE) payload[len] crc(2, LE) [signature(13)]
  v1: 0xFE len seq sysid compid msgid payload[len] crc(2, LE)
CRC = X.25 over everything after the magic byte up to the payload, plus the message's
CRC_EXTRA byte.
"""

from __future__ import annotations

import struct

from .codec import _mavlink

__all__ = [
    "MESSAGE_IDS",
    "crc_extra",
    "payload_struct",
    "x25crc",
    "build_v2",
    "build_v1",
    "recrc",
    "split",
]

MESSAGE_IDS: tuple[int, ...] = tuple(sorted(_mavlink.mavlink_map))
"""Every message id of the common dialect."""


def crc_extra(msg_id: int) -> int:
    """The CRC_EXTRA byte of ``msg_id`` (0 for ids the dialect does not know)."""
    cls = _mavlink.mavlink_map.get(msg_id)
    return 0 if cls is None else cls.crc_extra


def payload_struct(msg_id: int) -> struct.Struct | None:
    """The payload's wire layout (fields in wire order, MAVLink 2 extensions included),
    or None for an unknown id. ``.format`` tells where the floats ('f', 'd') are."""
    cls = _mavlink.mavlink_map.get(msg_id)
    return None if cls is None else cls.unpacker


def x25crc(data: bytes) -> int:
    """MAVLink's CRC-16/MCRF4XX (X.25) of ``data``."""
    return _mavlink.x25crc(bytearray(data)).crc


def build_v2(
    msg_id: int,
    payload: bytes,
    seq: int = 0,
    src_system: int = 1,
    src_component: int = 1,
    incompat_flags: int = 0,
    compat_flags: int = 0,
    length: int | None = None,
    extra: int | None = None,
    signature: bytes = b"",
) -> bytes:
    """A MAVLink 2 frame with a valid CRC for ``payload`` (``length`` overrides the length
    byte, ``extra`` the CRC_EXTRA: both make deliberately wrong frames)."""
    n = len(payload) if length is None else length
    header = struct.pack(
        "<BBBBBBBHB",
        0xFD,
        n & 0xFF,
        incompat_flags & 0xFF,
        compat_flags & 0xFF,
        seq & 0xFF,
        src_system & 0xFF,
        src_component & 0xFF,
        msg_id & 0xFFFF,
        (msg_id >> 16) & 0xFF,
    )
    crc = x25crc(header[1:] + payload + bytes([crc_extra(msg_id) if extra is None else extra & 0xFF]))
    return header + payload + struct.pack("<H", crc) + signature


def build_v1(msg_id: int, payload: bytes, seq: int = 0, src_system: int = 1, src_component: int = 1) -> bytes:
    """A MAVLink 1 frame (ids < 256) with a valid CRC."""
    header = struct.pack("<BBBBBB", 0xFE, len(payload) & 0xFF, seq & 0xFF, src_system & 0xFF, src_component & 0xFF, msg_id & 0xFF)
    crc = x25crc(header[1:] + payload + bytes([crc_extra(msg_id & 0xFF)]))
    return header + payload + struct.pack("<H", crc)


def split(frame: bytes) -> tuple[dict, bytes, bytes]:
    """(header fields, payload, trailer after the CRC) of a well-formed v1/v2 frame."""
    if frame[0] == 0xFD:
        magic, n, inc, comp, seq, sysid, compid, lo, hi = struct.unpack_from("<BBBBBBBHB", frame)
        hdr = dict(version=2, length=n, incompat_flags=inc, compat_flags=comp, seq=seq, src_system=sysid,
                   src_component=compid, msg_id=lo | (hi << 16))  # fmt: skip
        return hdr, frame[10 : 10 + n], frame[12 + n :]
    if frame[0] == 0xFE:
        magic, n, seq, sysid, compid, mid = struct.unpack_from("<BBBBBB", frame)
        hdr = dict(version=1, length=n, seq=seq, src_system=sysid, src_component=compid, msg_id=mid)
        return hdr, frame[6 : 6 + n], frame[8 + n :]
    raise ValueError(f"not a MAVLink frame (magic {frame[:1].hex()})")


def recrc(frame: bytes) -> bytes:
    """``frame`` with its CRC recomputed for its (possibly mutated) header and payload; the
    signature block, if any, is kept as it was (so it no longer matches)."""
    hdr, payload, trailer = split(frame)
    head_len = 10 if hdr["version"] == 2 else 6
    n = hdr["length"]
    body = frame[1 : head_len + n]
    crc = x25crc(body + bytes([crc_extra(hdr["msg_id"])]))
    return frame[: head_len + n] + struct.pack("<H", crc) + trailer
