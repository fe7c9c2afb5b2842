"""bench/escape_candidates.py, the escape's candidate table for one UAV: its first line is the command the kernel sent
(the tool's own arithmetic checked against kernels.escape_candidates on a real flight), and it says where the escape
was not active."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest


def _tool():
    spec = importlib.util.spec_from_file_location("escape_candidates", Path(__file__).parents[1] / "bench" / "escape_candidates.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# the failure fingerprint's flight (crossing N = 16 seed 2, UAV 3 failing into Hold at 10 s in a gust): UAV 4's escape
# acts at steps 22-24 and not at step 5
ARGS = ["--scenario", "crossing", "--n", "16", "--seed", "2", "--uav", "4", "--steps", "5,22,23,24", "--gust",
        "--fail-vehicle", "3", "--fail-at", "10"]


@pytest.mark.parametrize("backstop", ["{}", '{"escape_effort": 0.3}', '{"escape_tube_m_s2": 1.0}'])
def test_the_first_line_is_the_command_the_kernel_sent(capsys, backstop):
    # given the flight, and the escape's parameters as flown or changed
    # when the tool prints UAV 4's table at those steps
    done = _tool().run(ARGS + ["--backstop", backstop, "--top", "3"])
    out = capsys.readouterr().out
    # then every active step is reported, its first candidate line is what the kernel sent, and the quiet step is named
    assert [d["step"] for d in done] == [22, 23, 24]
    assert all(d["matches"] for d in done)
    assert out.count("the first line is the command the kernel sent") == 3
    assert out.count("  a1 (") == 9
    assert "not active at step(s) 5" in out
    # and the failed vehicle (braking into its Hold at 1 m/s, in the stream) is read with a tube exactly when it is on
    # (BackstopParams.escape_tube_m_s2: the controller's choice of tube entries, the kernel's and the tool's reading)
    assert ("tube True" in out) == ("escape_tube_m_s2" in backstop)
