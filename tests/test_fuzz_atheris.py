"""Coverage-guided fuzzing with atheris (optional dependency): a short libFuzzer run of the
vehicle's input path (``tests/fuzz_atheris_vehicle.py``) in its own process."""

from __future__ import annotations

import importlib.util
import re
import subprocess
from pathlib import Path

import pytest

from _net import PYTHON, REPO

pytestmark = pytest.mark.skipif(importlib.util.find_spec("atheris") is None, reason="atheris not installed (pip install atheris)")

RUNS = 50_000


def test_atheris_coverage_guided_vehicle_input_fuzz(tmp_path, capsys):
    harness = Path(__file__).with_name("fuzz_atheris_vehicle.py")
    out = subprocess.run(
        [PYTHON, str(harness), f"-runs={RUNS}", "-max_len=300", "-seed=1", str(tmp_path)],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    text = out.stdout + out.stderr
    assert out.returncode == 0, text[-4000:]
    assert f"Done {RUNS} runs" in text
    cov = [int(m) for m in re.findall(r"cov: (\d+)", text)]
    assert cov and cov[-1] > 250  # it explored the handlers, not just the CRC check
    with capsys.disabled():
        print(f"\natheris: {RUNS} inputs, final coverage {cov[-1]} edges, corpus {len(list(tmp_path.iterdir()))} files")
