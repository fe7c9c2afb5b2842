"""Coverage-guided fuzzing (atheris / libFuzzer) of the vehicle's input path: datagram
-> ``MavCodec.decode_datagram`` -> ``MockVehicle.handle`` -> ``tick``, in process with a
fake clock. Each input is a datagram; the vehicle starts armed in OFFBOARD so setpoints
reach the plant. An input whose first byte is < 0xF0 is a *payload*: the first byte picks one
of the messages the vehicle handles, the rest is its payload, and the harness wraps it in a
MAVLink 2 frame with a valid CRC (libFuzzer could not find CRCs itself); otherwise the input
is sent as raw bytes. Checked after every input: the plant state is finite and no handler
raised (``handle`` turns exceptions into an "internal error" rejection, which fails here).

Run (libFuzzer flags; it exits when done, so run it as its own process):

    .venv/bin/python tests/fuzz_atheris_vehicle.py -runs=200000 -max_len=600 -seed=1

``tests/test_fuzz_atheris.py`` runs a short one. atheris is optional (``pip install atheris``).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import atheris

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

with atheris.instrument_imports(include=["mavlink_bridge", "mock_vehicle"]):  # not pymavlink: slow, not ours
    from mavlink_bridge import PX4_OFFBOARD, Received, SetPositionTargetLocalNed
    from mavlink_bridge.codec import MavCodec
    from mavlink_bridge.frames import build_v2
    from mock_vehicle.vehicle import MockVehicle, VehicleConfig

from fuzz_mavlink import HANDLED_IDS  # noqa: E402

import numpy as np  # noqa: E402


class _Clock:
    t = 1000.0

    def __call__(self) -> float:
        return self.t


CLOCK = _Clock()
SENT: list = []
CODEC = MavCodec(1, 1)


def _fresh_vehicle() -> MockVehicle:
    v = MockVehicle(VehicleConfig(), lambda m, p: SENT.append(m), clock=CLOCK)
    good = SetPositionTargetLocalNed(0, 1, 1, 1, 3135, 0, 0, 0, 0, 0, 0, 0.5, 0.5, 0, 0, 0)
    for _ in range(15):
        v.handle(Received(good, 1, 191))
        CLOCK.t += 0.1
        v.tick()
    v.armed = True
    v._request_mode(PX4_OFFBOARD)
    return v


VEHICLE = _fresh_vehicle()
N_INPUTS = 0


def test_one_input(data: bytes) -> None:
    global VEHICLE, N_INPUTS
    N_INPUTS += 1
    if N_INPUTS % 2000 == 0:  # start over now and then, so OFFBOARD paths stay reachable
        VEHICLE = _fresh_vehicle()
    if data and data[0] < 0xF0:
        data = build_v2(HANDLED_IDS[data[0] % len(HANDLED_IDS)], data[1:256], src_system=1, src_component=191)
    for r in CODEC.decode_datagram(data):
        VEHICLE.handle(r)
    CLOCK.t += 0.05
    VEHICLE.tick()
    SENT.clear()
    if not np.all(np.isfinite(VEHICLE.state)):
        raise AssertionError(f"non-finite state {VEHICLE.state} after {data!r}")
    bad = [k for k in VEHICLE.rejects.counts if k.startswith("internal error") or k.startswith("non-finite")]
    if bad:
        raise AssertionError(f"{bad} after {data!r}")
    if not math.isfinite(VEHICLE.z_m):
        raise AssertionError("non-finite altitude")


def main() -> None:
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
