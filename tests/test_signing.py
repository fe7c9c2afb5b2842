"""MAVLink 2 signing, in process (issue 10): key files, the signature check with its
replay protection, and the mock's and the link's policy for unsigned input."""

from __future__ import annotations

import os
import time
import unittest.mock

import pytest

from mavlink_bridge import (
    PX4_HOLD,
    CommandLong,
    Heartbeat,
    LocalPositionNed,
    MavCmd,
    SigningConfig,
    SigningKeyError,
    load_signing_key,
    write_signing_key,
)
from mavlink_bridge.codec import MavCodec
from mavlink_bridge.frames import recrc
from mavlink_bridge.signing import SIG_BAD, SIG_REPLAY, SIG_UNCHECKED, SIG_UNSIGNED, SIG_VALID, signing_timestamp_now
from mock_vehicle.vehicle import MockVehicle, VehicleConfig

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))


# ---------------------------------------------------------------- key files
def test_key_file_round_trip_and_mode_600(tmp_path):
    path = tmp_path / "mav.key"
    key = write_signing_key(path)
    assert len(key) == 32 and (os.stat(path).st_mode & 0o777) == 0o600
    assert path.read_text().strip() == key.hex() and len(path.read_text().strip()) == 64
    assert load_signing_key(path) == key


def test_missing_key_file_names_the_file_and_how_to_create_one(tmp_path):
    path = tmp_path / "nope.key"
    with pytest.raises(SigningKeyError, match=r"nope\.key does not exist.*--generate"):
        load_signing_key(path)


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o660, 0o644, 0o700 | 0o001])
def test_group_or_other_readable_key_file_is_refused_with_chmod_600(tmp_path, mode):
    path = tmp_path / "loose.key"
    write_signing_key(path)
    os.chmod(path, mode)
    with pytest.raises(SigningKeyError, match=rf"loose\.key is accessible by group/others \(mode {mode:#o}\); fix it with: chmod 600 .*loose\.key"):
        load_signing_key(path)


@pytest.mark.parametrize("content", [b"", b"abc", b"zz" * 32, KEY, KEY.hex().encode() + b"00", KEY.hex()[:-2].encode()])
def test_malformed_key_file_is_refused(tmp_path, content):
    path = tmp_path / "bad.key"
    path.write_bytes(content)
    os.chmod(path, 0o600)
    with pytest.raises(SigningKeyError, match="must hold exactly 64 hexadecimal characters"):
        load_signing_key(path)


def test_key_file_may_end_with_a_newline_and_use_upper_case(tmp_path):
    path = tmp_path / "k"
    path.write_text("  " + KEY.hex().upper() + "\n")
    os.chmod(path, 0o400)
    assert load_signing_key(path) == KEY


def test_existing_key_file_is_never_overwritten(tmp_path):
    path = tmp_path / "k"
    write_signing_key(path, KEY)
    with pytest.raises(FileExistsError):
        write_signing_key(path)
    assert load_signing_key(path) == KEY


# ---------------------------------------------------------------- signatures
def _hb() -> Heartbeat:
    return Heartbeat(type=2, autopilot=12, base_mode=0, custom_mode=0, system_status=3)


def test_signed_packets_verify_only_under_the_same_key_and_only_once():
    alice = MavCodec(1, 191, SigningConfig(KEY, link_id=7))
    bob = MavCodec(1, 1, SigningConfig(KEY))
    eve = MavCodec(1, 1, SigningConfig(OTHER_KEY))
    plain = MavCodec(1, 1)
    pkt = alice.encode(_hb())
    assert pkt[2] & 0x01 and len(pkt) > 13 and pkt[-13] == 7  # signed flag, link id
    ts = int.from_bytes(pkt[-12:-6], "little")
    assert abs(ts - signing_timestamp_now()) < 5 * 100_000  # 10 us units since 2015, now
    [r] = bob.decode(pkt)
    assert r.signature == SIG_VALID and r.signed_ok and r.msg.type == 2
    [again] = bob.decode(pkt)
    assert again.signature == SIG_REPLAY  # the same packet twice: a replay
    assert eve.decode(pkt)[0].signature == SIG_BAD
    assert plain.decode(pkt)[0].signature == SIG_UNCHECKED  # decodes, but cannot check
    assert bob.decode(plain.encode(_hb()))[0].signature == SIG_UNSIGNED
    # a later packet of the same stream is fresh again
    assert bob.decode(alice.encode(_hb()))[0].signature == SIG_VALID


def test_a_forged_far_future_timestamp_does_not_lock_out_the_genuine_stream():
    """pymavlink's own check records a stream's timestamp before checking the signature;
    ours only advances on a valid one, so a forgery cannot make genuine packets replays."""
    alice = MavCodec(1, 191, SigningConfig(KEY))
    bob = MavCodec(1, 1, SigningConfig(KEY))
    eve = MavCodec(1, 191, SigningConfig(OTHER_KEY))
    eve._tx.signing.timestamp = 2**48 - 10  # far future, same (link, system, component) stream
    assert bob.decode(eve.encode(_hb()))[0].signature == SIG_BAD
    assert bob.decode(alice.encode(_hb()))[0].signature == SIG_VALID


def test_altered_signed_packet_is_bad_and_old_new_stream_is_a_replay():
    alice = MavCodec(1, 191, SigningConfig(KEY))
    bob = MavCodec(1, 1, SigningConfig(KEY))
    pkt = bytearray(alice.encode(CommandLong(1, 1, MavCmd.COMPONENT_ARM_DISARM, (1.0,) + (0.0,) * 6)))
    # flip a payload byte and fix the CRC: the CRC passes, the signature does not
    pkt[12] ^= 0x01
    assert bob.decode(recrc(bytes(pkt)))[0].signature == SIG_BAD
    # a capture more than a minute old, on a stream the receiver has not seen yet
    with unittest.mock.patch("mavlink_bridge.codec.signing_timestamp_now", lambda: signing_timestamp_now(time.time() - 120)):
        old = MavCodec(1, 192, SigningConfig(KEY))  # a sender whose clock says two minutes ago
        stale = old.encode(_hb())
    assert bob.decode(stale)[0].signature == SIG_REPLAY


# ---------------------------------------------------------------- the mock's policy
class _Sent(list):
    def __call__(self, msg, port):
        self.append(msg)


def _signed_mock():
    sent = _Sent()
    v = MockVehicle(VehicleConfig(), sent, require_signed=True)
    return v, sent


def test_mock_with_signing_ignores_unsigned_and_badly_signed_commands_once_logged_per_kind(caplog):
    v, sent = _signed_mock()
    rx = MavCodec(1, 1, SigningConfig(KEY))  # the vehicle's receive side
    arm = CommandLong(1, 1, MavCmd.COMPONENT_ARM_DISARM, (1.0,) + (0.0,) * 6)
    with caplog.at_level("WARNING", logger="mock_vehicle"):
        for codec in (MavCodec(1, 191), MavCodec(1, 191, SigningConfig(OTHER_KEY))):
            for _ in range(50):
                for r in rx.decode(codec.encode(arm)):
                    v.handle(r)
    assert not v.armed and sent == []  # not even a COMMAND_ACK
    assert v.rejects.counts == {"unsigned COMMAND_LONG": 50, "bad signature COMMAND_LONG": 50}
    lines = [rec.getMessage() for rec in caplog.records if rec.getMessage().startswith("rejected")]
    assert len(lines) == 2, lines  # once per kind, not once per frame
    legit = MavCodec(1, 191, SigningConfig(KEY))
    for r in rx.decode(legit.encode(arm)):
        v.handle(r)
    assert v.armed and sent and sent[0].MSG_NAME == "HEARTBEAT" and v.mode == PX4_HOLD


def test_mock_without_signing_accepts_unsigned_as_before():
    sent = _Sent()
    v = MockVehicle(VehicleConfig(), sent)
    for r in MavCodec(1, 1).decode(MavCodec(1, 191).encode(CommandLong(1, 1, MavCmd.COMPONENT_ARM_DISARM, (1.0,) + (0.0,) * 6))):
        v.handle(r)
    assert v.armed


def test_signed_codec_round_trips_telemetry_values():
    a = MavCodec(1, 1, SigningConfig(KEY))
    b = MavCodec(1, 191, SigningConfig(KEY))
    lp = LocalPositionNed(1234, 1.5, -2.5, -10.0, 0.25, -0.5, 0.0)
    [r] = b.decode(a.encode(lp))
    assert r.signed_ok and (r.msg.x_m, r.msg.y_m, r.msg.time_boot_ms) == (1.5, -2.5, 1234)
