"""The simulator's output for fixed seeds is bit-identical to a stored fingerprint.

The fingerprint (``tests/data/sim_fingerprints.json``) holds, per configuration, every key of
``metrics.json`` but the wall time, and a SHA-256 of every array of ``trajectories.npz``. It was
written before the controller package was split into rooms (issue 20), so a move that changes a
single bit of any flight fails here. Regenerate it only for a change that is *meant* to change
flights, and say so in the commit:

    .venv/bin/python tests/test_sim_fingerprint.py --write

One array is compared by value instead of by bits (``APPROX``): ``w_H_ref``, the reference UAV's value-model
weights, which the online NGD update (Algorithms 3/4) computes through numpy reductions whose last bits depend on
the host's SIMD code path (measured: on another host this array alone changed bits while every trajectory, command
and metric stayed bit-identical). Its sum, L2 norm and largest magnitude are compared to a relative 1e-6: a change
of behaviour moves them far more.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).with_name("data") / "sim_fingerprints.json"

# (scenario, mode, preset, n, seed, extra args): every controller family the simulator flies.
CONFIGS = {
    "paper-mfg-default-n9-s3": ["--scenario", "paper", "--mode", "mfg", "--preset", "default", "--n", "9", "--seed", "3"],
    "crossing-hjb100-default-n16-s5": ["--scenario", "crossing", "--mode", "hjb", "--range-m", "100", "--preset", "default",
                                       "--n", "16", "--seed", "5"],
    "crossing-mfg-default-n16-s2-fail": ["--scenario", "crossing", "--mode", "mfg", "--preset", "default", "--n", "16",
                                         "--seed", "2", "--fail-vehicle", "3", "--fail-at", "10", "--gust"],
    "dense-mfg-default-n16-s4": ["--scenario", "dense", "--mode", "mfg", "--preset", "default", "--n", "16", "--seed", "4"],
    "paper-mfg-paper-n9-s1": ["--scenario", "paper", "--mode", "mfg", "--preset", "paper", "--n", "9", "--seed", "1"],
    "paper-hjb1-paper-n9-s1": ["--scenario", "paper", "--mode", "hjb", "--range-m", "1", "--preset", "paper", "--n", "9",
                               "--seed", "1"],
}
STEPS = "60"
APPROX = ("w_H_ref",)       # compared by value (module docstring)


def _summary(a: np.ndarray) -> list[float]:
    a = np.asarray(a, dtype=np.float64)
    return [float(a.sum()), float(np.linalg.norm(a)), float(np.max(np.abs(a))) if a.size else 0.0]


def fingerprint(run_dir: Path) -> dict:
    """metrics.json without its wall time, and the SHA-256 of each trajectory array (dtype, shape, bytes)."""
    metrics = json.loads((run_dir / "metrics.json").read_text())
    metrics.pop("wall_s", None)
    arrays, approx = {}, {}
    with np.load(run_dir / "trajectories.npz") as z:
        for name in sorted(z.files):
            a = np.ascontiguousarray(z[name])
            if name in APPROX:
                approx[name] = _summary(a)
                continue
            h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
            arrays[name] = h.hexdigest()
    return {"metrics": metrics, "arrays": arrays, "approx": approx}


def fly(args: list[str], out: Path) -> dict:
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "sim", "--no-progress", "--steps", STEPS,
                           "--out", str(out), *args], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return fingerprint(out)


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_simulator_output_is_bit_identical_to_the_stored_fingerprint(tmp_path, name):
    stored = json.loads(DATA.read_text())[name]
    got = fly(CONFIGS[name], tmp_path / name)
    # every stored key identical; a key added later (a new array or metric) does not break the comparison
    bits = {k: v for k, v in stored["arrays"].items() if k not in APPROX}
    assert {k: got["arrays"].get(k, "<missing>") for k in bits} == bits, f"{name}: trajectories changed"
    for k, want in stored.get("approx", {}).items():
        assert k in got["approx"] and np.allclose(got["approx"][k], want, rtol=1e-6, atol=0.0), f"{name}: {k} changed"
    assert _stored_part(got["metrics"], stored["metrics"]) == stored["metrics"], f"{name}: metrics changed"


def _stored_part(got, stored):
    """got restricted to the keys stored (at every depth of nested dicts): a key added later does not count."""
    if isinstance(stored, dict) and isinstance(got, dict):
        return {k: _stored_part(got[k], v) if k in got else "<missing>" for k, v in stored.items()}
    return got


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit(__doc__)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = {name: fly(args, Path(tmp) / name) for name, args in sorted(CONFIGS.items())}
    DATA.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"wrote {DATA} ({len(out)} configurations)")
