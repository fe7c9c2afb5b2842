"""MAVLink frame fuzzer (issue 10 "Bad input, fuzzed").

Generates random and mutated MAVLink frames from a seeded ``random.Random`` and sends them
over loopback UDP to a running ``mock-vehicle`` process and to a controller-side
``VehicleLink``; ``tests/test_fuzz_mavlink.py`` runs it in CI, and the long run is

    .venv/bin/python -m tests.fuzz_mavlink --frames 1000000 [--target mock|link|both] [--seed 1]

(from the repository root). It prints one JSON line per target: frames sent, frames by
kind, datagrams the target reported, wall time, and the checks made afterwards.

Frame kinds (``KINDS``), all with a valid CRC unless the kind says otherwise:
  mutated     a real packet built by pymavlink (through ``MavCodec``) for a message the
              targets handle, 1-4 payload bytes flipped/overwritten, CRC recomputed
  fields      a handled message's payload packed field by field with hostile values
              (NaN, +-inf, +-3.4e38, huge integers, 0, -1 ...), mostly aimed at system 1
  random_id   any message id of the dialect (or an unknown one) with random payload bytes
  truncated   a valid frame cut short
  bad_length  the length byte disagrees with the payload
  bad_crc     a valid frame with a wrong CRC (or a wrong CRC_EXTRA)
  signed      the signed flag set and a random 13-byte signature block
  v1          MAVLink 1 frames with random payloads
  garbage     random bytes, often starting with a magic byte 0xFD/0xFE
  multi       2-5 of the above in one datagram
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
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mavlink_bridge import (  # noqa: E402
    CommandAck,
    CommandInt,
    CommandLong,
    Heartbeat,
    LocalPositionNed,
    MavCmd,
    ParamRequestList,
    ParamRequestRead,
    ParamSet,
    ParamValue,
    SetMode,
    SetPositionTargetLocalNed,
)
from mavlink_bridge.codec import MAVLINK_MSG_ID, MavCodec  # noqa: E402
from mavlink_bridge.frames import MESSAGE_IDS, build_v1, build_v2, payload_struct, recrc, split  # noqa: E402

__all__ = ["FrameFuzzer", "KINDS", "SYNC_SYSTEM", "fuzz_mock", "fuzz_link"]

KINDS = ("mutated", "fields", "random_id", "truncated", "bad_length", "bad_crc", "signed", "v1", "garbage", "multi")
SYNC_SYSTEM = 250
"""System id the fuzz driver's synchronisation requests come from; fuzz frames never use it."""

# messages the targets act on (vehicle side and controller side)
HANDLED = [
    "SET_POSITION_TARGET_LOCAL_NED", "COMMAND_LONG", "COMMAND_INT", "SET_MODE", "PARAM_SET", "PARAM_REQUEST_READ",
    "PARAM_REQUEST_LIST", "HEARTBEAT", "LOCAL_POSITION_NED", "COMMAND_ACK", "PARAM_VALUE", "ATTITUDE",
    "GLOBAL_POSITION_INT", "SYS_STATUS", "EXTENDED_SYS_STATE", "HOME_POSITION", "STATUSTEXT", "AUTOPILOT_VERSION",
]  # fmt: skip
HANDLED_IDS = [MAVLINK_MSG_ID[n] for n in HANDLED]

F32_MAX = 3.4028234663852886e38
HOSTILE_FLOATS = [math.nan, -math.nan, math.inf, -math.inf, F32_MAX, -F32_MAX, 1e30, -1e30, 1e-45, 0.0, -0.0, 1.0, -1.0,
                  2.0, 6.0, 4.0, 21196.0, 400.0, 176.0, 129.0, 1e6, 1e5 + 1]  # fmt: skip
COMMANDS = [int(c) for c in MavCmd] + [0, 1, 65535, 31000]
INT_LIMITS = {"B": (0, 255), "b": (-128, 127), "H": (0, 65535), "h": (-32768, 32767), "I": (0, 2**32 - 1),
              "i": (-(2**31), 2**31 - 1), "Q": (0, 2**64 - 1), "q": (-(2**63), 2**63 - 1)}  # fmt: skip


def _fields(fmt: str) -> list[tuple[str, int]]:
    """struct format -> [(type char, count)] ('16s' stays one string field)."""
    out, num = [], ""
    for ch in fmt.lstrip("<>=!@"):
        if ch.isdigit():
            num += ch
            continue
        n = int(num) if num else 1
        num = ""
        if ch == "s":
            out.append(("s", n))
        else:
            out.extend([(ch, 1)] * n)
    return out


class FrameFuzzer:
    """Seeded generator of hostile MAVLink frames (see module docstring)."""

    def __init__(self, seed: int = 0, target_system: int = 1) -> None:
        self.rng = random.Random(seed)
        self.target_system = target_system
        self.counts = {k: 0 for k in KINDS}
        self._codecs = [MavCodec(s, c) for s, c in ((1, 1), (1, 191), (2, 1), (255, 190))]
        self._layouts = {mid: (payload_struct(mid), _fields(payload_struct(mid).format)) for mid in HANDLED_IDS}

    # --- building blocks
    def _src(self) -> tuple[int, int]:
        r = self.rng
        s = r.choice([1, 1, 1, 2, 0, 255, r.randrange(256)])
        return (s if s != SYNC_SYSTEM else 1), r.choice([1, 1, 191, 0, r.randrange(256)])

    def _hostile_value(self, ch: str, name_hint: int):
        r = self.rng
        if ch in "fd":
            return r.choice(HOSTILE_FLOATS) if r.random() < 0.7 else r.uniform(-1e3, 1e3)
        if ch == "s":
            return r.choice([b"", b"SIM_ARM_DENY", b"COM_OF_LOSS_T", b"MPC_ACC_HOR_MAX", b"SIM_WIND_C0",
                             r.randbytes(16), b"\xff" * 16])  # fmt: skip
        lo, hi = INT_LIMITS[ch]
        if name_hint == 0 and ch in "BH":  # likely a target id / command / frame: aim at the vehicle
            return r.choice([0, self.target_system, self.target_system, 1, lo, hi, r.randint(lo, hi)])
        return r.choice([lo, hi, 0, 1, r.randint(lo, hi)])

    def _typed_message(self):
        """A real typed message with plausible-to-hostile fields."""
        r = self.rng
        ts = self.target_system
        f = lambda: r.choice(HOSTILE_FLOATS) if r.random() < 0.5 else r.uniform(-50, 50)  # noqa: E731
        k = r.randrange(9)
        if k == 0:
            return SetPositionTargetLocalNed(r.randrange(2**32), r.choice([0, ts]), r.choice([0, 1]), r.choice([1, 8, 7, 0]),
                                             r.choice([3135, 0x0DC7, 0x0DF8, 0, 0xFFFF, r.randrange(65536)]),
                                             *(f() for _ in range(11)))  # fmt: skip
        if k == 1:
            return CommandLong(r.choice([0, ts]), r.choice([0, 1]), r.choice(COMMANDS), tuple(f() for _ in range(7)), r.randrange(256))
        if k == 2:
            return CommandInt(r.choice([0, ts]), r.choice([0, 1]), r.choice(COMMANDS), r.randrange(256), tuple(f() for _ in range(4)),
                              r.randint(-(2**31), 2**31 - 1), r.randint(-(2**31), 2**31 - 1), f())  # fmt: skip
        if k == 3:
            return SetMode(r.choice([0, ts]), r.randrange(256), r.choice([6 << 16, 4 << 16 | 3 << 24, r.randrange(2**32)]))
        if k == 4:
            return ParamSet(r.choice([0, ts]), 1, r.choice(["SIM_ARM_DENY", "COM_OF_LOSS_T", "MPC_ACC_HOR_MAX", "SIM_WIND_C0", "X"]), f(), 9)
        if k == 5:
            return ParamRequestRead(r.choice([0, ts]), 1, "SIM_WIND_VN", r.choice([-1, 0, 9, 10, 32767]))
        if k == 6:
            return LocalPositionNed(r.randrange(2**32), *(f() for _ in range(6)))
        if k == 7:
            return Heartbeat(r.randrange(256), r.randrange(256), r.randrange(256), r.randrange(2**32), r.randrange(256))
        if k == 8:
            return CommandAck(r.choice(COMMANDS), r.randrange(256), r.choice([0, 1]), r.choice([0, 191]))
        return ParamRequestList(ts, 1)

    def _valid_frame(self) -> bytes:
        codec = self.rng.choice(self._codecs)
        try:
            return codec.encode(self._typed_message())
        except (struct.error, ValueError, OverflowError, TypeError):
            return codec.encode(ParamRequestList(self.target_system, 1))

    def _fields_frame(self) -> bytes:
        r = self.rng
        mid = r.choice(HANDLED_IDS)
        st, fields = self._layouts[mid]
        values = []
        for i, (ch, n) in enumerate(fields):
            v = self._hostile_value(ch, 0 if i >= len(fields) - 4 else 1)
            values.append(v)
        try:
            payload = st.pack(*values)
        except struct.error:
            payload = r.randbytes(st.size)
        if r.random() < 0.5:  # MAVLink 2 trailing-zero truncation, as senders do
            payload = payload.rstrip(b"\x00") or b"\x00"
        s, c = self._src()
        return build_v2(mid, payload, r.randrange(256), s, c)

    def frame(self) -> tuple[str, bytes]:
        """One datagram: (kind, bytes)."""
        r = self.rng
        kind = r.choices(KINDS, weights=(25, 25, 10, 8, 6, 6, 6, 5, 5, 4))[0]
        self.counts[kind] += 1
        if kind == "mutated":
            f = bytearray(self._valid_frame())
            hdr, payload, _ = split(bytes(f))
            head = 10 if hdr["version"] == 2 else 6
            for _ in range(r.randint(1, 4)):
                if payload:
                    i = head + r.randrange(len(payload))
                    f[i] = r.randrange(256) if r.random() < 0.5 else f[i] ^ (1 << r.randrange(8))
            return kind, recrc(bytes(f))
        if kind == "fields":
            return kind, self._fields_frame()
        if kind == "random_id":
            mid = r.choice(MESSAGE_IDS) if r.random() < 0.9 else r.randrange(2**24)
            s, c = self._src()
            return kind, build_v2(mid, r.randbytes(r.randint(1, 255)), r.randrange(256), s, c)
        if kind == "truncated":
            f = self._valid_frame()
            return kind, f[: r.randrange(1, len(f))]
        if kind == "bad_length":
            f = self._valid_frame()
            hdr, payload, _ = split(f)
            s, c = self._src()
            return kind, build_v2(hdr["msg_id"], payload, 0, s, c, length=r.choice([0, 255, max(0, len(payload) - 1), len(payload) + 1]))
        if kind == "bad_crc":
            f = bytearray(self._valid_frame())
            if r.random() < 0.5:
                hdr, payload, _ = split(bytes(f))
                return kind, build_v2(hdr["msg_id"], payload, extra=r.randrange(256))
            f[-2] ^= 1 + r.randrange(255)
            return kind, bytes(f)
        if kind == "signed":
            mid = r.choice(HANDLED_IDS)
            st, _ = self._layouts[mid]
            s, c = self._src()
            return kind, build_v2(mid, r.randbytes(st.size), 0, s, c, incompat_flags=1,
                                  signature=r.randbytes(r.choice([13, 13, 13, 0, 5])))  # fmt: skip
        if kind == "v1":
            mid = r.choice([m for m in HANDLED_IDS if m < 256])
            s, c = self._src()
            return kind, build_v1(mid, r.randbytes(r.randint(0, 60)), 0, s, c)
        if kind == "garbage":
            n = r.randint(1, 300)
            g = r.randbytes(n)
            return kind, (bytes([r.choice([0xFD, 0xFE])]) + g) if r.random() < 0.6 else g
        return "multi", b"".join(self.frame()[1] for _ in range(r.randint(2, 5)))  # the parts count as their own kinds


# ------------------------------------------------------------------ drivers
def _sync_request(tag: int, signing=None) -> bytes:
    """REQUEST_MESSAGE(AUTOPILOT_VERSION) from (SYNC_SYSTEM, tag): the vehicle answers it
    with a COMMAND_ACK addressed to (SYNC_SYSTEM, tag) once it has read every datagram
    sent before it (one socket, one reader, in order)."""
    return MavCodec(SYNC_SYSTEM, tag, signing).encode(CommandLong(0, 0, MavCmd.REQUEST_MESSAGE, (148.0,) + (0.0,) * 6))


def fuzz_mock(vehicle_listen_port: int, frames: int, seed: int = 0, chunk: int = 400, sync_timeout_s: float = 10.0,
              sock: socket.socket | None = None, signing=None) -> dict:  # fmt: skip
    """Fuzz the mock vehicle whose onboard link sends to 127.0.0.1:``vehicle_listen_port``
    (this function binds that port, learns the vehicle's address from its telemetry, then
    sends ``frames`` datagrams in chunks, each followed by a sync request it waits for).
    ``signing``: the vehicle's SigningConfig, used for the sync requests only (the fuzz
    frames themselves are unsigned or carry random signatures). Returns a report dict."""
    own = sock is None
    if own:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        sock.bind(("127.0.0.1", vehicle_listen_port))
    rx = MavCodec(SYNC_SYSTEM, 0, signing)
    sock.settimeout(sync_timeout_s)
    try:
        _, vehicle = sock.recvfrom(65535)  # its first telemetry datagram: the address to attack
        fz = FrameFuzzer(seed)
        t0 = time.monotonic()
        sent = syncs = sync_timeouts = 0
        tag = 0
        while sent < frames:
            for _ in range(min(chunk, frames - sent)):
                sock.sendto(fz.frame()[1], vehicle)
                sent += 1
            tag = tag % 250 + 1
            sock.sendto(_sync_request(tag, signing), vehicle)
            deadline = time.monotonic() + sync_timeout_s
            ok = False
            while not ok and time.monotonic() < deadline:
                try:
                    data, _ = sock.recvfrom(65535)
                except socket.timeout:
                    break
                for r in rx.decode_datagram(data):
                    m = r.msg
                    if (signing is None or r.signed_ok) and isinstance(m, CommandAck) and m.command == MavCmd.REQUEST_MESSAGE and (m.target_system, m.target_component) == (SYNC_SYSTEM, tag):
                        ok = True
            syncs += ok
            sync_timeouts += not ok
        wall_s = time.monotonic() - t0
        return dict(target="mock", frames=sent, kinds=fz.counts, syncs=syncs, sync_timeouts=sync_timeouts, wall_s=round(wall_s, 2),
                    frames_per_s=round(sent / wall_s), seed=seed)  # fmt: skip
    finally:
        if own:
            sock.close()


def fuzz_link(link, frames: int, seed: int = 0, chunk: int = 400, sync_timeout_s: float = 10.0) -> dict:
    """Fuzz a listening ``VehicleLink`` (``udpin:127.0.0.1:PORT``) from a fresh UDP socket,
    in chunks, each followed by a valid LOCAL_POSITION_NED from the link's target whose
    ``time_boot_ms`` is a marker the driver waits to see (the link has read the chunk)."""
    port = link.port.transport.local_address[1]
    fz = FrameFuzzer(seed, target_system=link.target_system)
    vehicle = MavCodec(link.target_system, link.target_component)
    t0 = time.monotonic()
    sent = syncs = sync_timeouts = 0
    marker = 4_000_000_000
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        while sent < frames:
            for _ in range(min(chunk, frames - sent)):
                sock.sendto(fz.frame()[1], ("127.0.0.1", port))
                sent += 1
            marker += 1
            sock.sendto(vehicle.encode(LocalPositionNed(marker, 1.0, 2.0, -10.0, 0.0, 0.0, 0.0)), ("127.0.0.1", port))
            m = marker
            ok = link.wait_for(LocalPositionNed, lambda p: p.time_boot_ms == m, sync_timeout_s) is not None
            syncs += ok
            sync_timeouts += not ok
    wall_s = time.monotonic() - t0
    return dict(target="link", frames=sent, kinds=fz.counts, syncs=syncs, sync_timeouts=sync_timeouts, wall_s=round(wall_s, 2),
                frames_per_s=round(sent / wall_s), seed=seed)  # fmt: skip


def _main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.fuzz_mavlink", description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1_000_000, help="frames per target")
    ap.add_argument("--target", choices=["mock", "link", "both"], default="both")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import test_fuzz_mavlink as t  # the same checks as the CI test

    if args.target in ("mock", "both"):
        import tempfile

        print(json.dumps(t.run_mock_fuzz(args.frames, args.seed, Path(tempfile.mkdtemp(prefix="fuzz-mock-")))), flush=True)
    if args.target in ("link", "both"):
        print(json.dumps(t.run_link_fuzz(args.frames, args.seed)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
