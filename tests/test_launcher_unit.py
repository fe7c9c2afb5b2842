"""The swarm launcher's start-up budget and its start-up failure report (no processes)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from mfg_swarm.launcher import _Child, _startup_report, default_startup_timeout_s


def test_startup_budget_grows_with_n_and_load_and_is_bounded():
    quiet = [default_startup_timeout_s(n, cores=2, load1=0.0) for n in (4, 25, 49, 81, 253)]
    assert quiet[0] == 120.0 and quiet == sorted(quiet) and quiet[3] > 200.0
    assert default_startup_timeout_s(81, cores=2, load1=20.0) > default_startup_timeout_s(81, cores=2, load1=2.0)
    assert default_startup_timeout_s(81, cores=8, load1=0.0) < quiet[3]
    assert default_startup_timeout_s(253, cores=1, load1=500.0) == 1800.0


def test_startup_report_names_stages_and_the_last_log_line(tmp_path):
    """Given controllers stuck at different start-up stages, the report groups them by the last
    stage each logged and quotes a stuck controller's last stderr line."""
    children = []
    for i in range(3):
        log = tmp_path / f"controller{i}.log"
        children.append(_Child(f"controller{i}", [sys.executable, "-c", f"print('waiting for the t = 0 exchange {i}')"], log))
    for c in children:
        c.p.wait(30)
        c.close()
    status = [{"vehicle_found": True}, {"vehicle_found": True, "t0_exchange": True, "armed": True, "offboard": True}, {}]
    text = _startup_report(children, status, [])
    assert "1 controller(s) last at 'vehicle_found': [0]" in text
    assert "last at 'nothing logged (process starting)': [2]" in text
    assert "controller0 (exit 0: waiting for the t = 0 exchange 0" in text
    assert "[1]" not in text
