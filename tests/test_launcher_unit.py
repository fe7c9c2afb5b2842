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


def test_controller_status_reads_step_heads_and_full_events(tmp_path):
    """Given a controller log written by ControllerLog (events, step records with arrays, a
    step record in another key order, a truncated last line), the launcher's incremental
    status reader gets every event, the newest step and time, and keeps the partial line."""
    import json

    import numpy as np

    from mfg_autopilot.runtime.autopilot import ControllerLog
    from mfg_swarm.launcher import _controller_status

    path = tmp_path / "controller0.jsonl"
    clog = ControllerLog(str(path))
    clog.event("armed")
    clog.write({"type": "step", "step": 3, "time_s": 1.5, "state": np.arange(4.0), "w_H": np.ones(54)})
    clog.event("offboard")
    clog.close()
    state, offsets = [dict()], [0]
    _controller_status([path], offsets, state)
    assert state[0] == {"armed": True, "offboard": True, "step": 3, "time_s": 1.5}
    with open(path, "a") as fh:
        fh.write(json.dumps({"time_s": 2.0, "type": "step", "step": 4}) + "\n" + '{"type":"step","step":5,"ti')
    _controller_status([path], offsets, state)
    assert (state[0]["step"], state[0]["time_s"]) == (4, 2.0)
    with open(path, "a") as fh:
        fh.write('me_s":2.5,"state":[0,0,0,0]}\n{"type":"end","reason":"mission_time"}\n')
    _controller_status([path], offsets, state)
    assert (state[0]["step"], state[0]["time_s"], state[0]["end"]) == (5, 2.5, "mission_time")


def test_bytecode_cache_for_children_when_byte_code_writing_is_off(tmp_path, monkeypatch):
    """Given PYTHONDONTWRITEBYTECODE (as in some CI sandboxes), the launcher compiles the
    children's modules once into a private 0700 cache and hands the children its prefix; without
    the variable the children inherit the environment unchanged (None)."""
    import os
    import stat
    import tempfile

    from mfg_swarm import launcher

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.delenv("PYTHONPYCACHEPREFIX", raising=False)
    monkeypatch.delenv("PYTHONDONTWRITEBYTECODE", raising=False)
    assert launcher._bytecode_cache_env(sys.executable, tmp_path / "warm.log") is None
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    env = launcher._bytecode_cache_env(sys.executable, tmp_path / "warm.log")
    prefix = Path(env["PYTHONPYCACHEPREFIX"])
    assert prefix.parent == tmp_path and stat.S_IMODE(prefix.stat().st_mode) == 0o700
    assert env["PYTHONDONTWRITEBYTECODE"] == "1"          # the children still write nothing themselves
    runtime_src = Path(launcher.__file__).resolve().parent.parent / "mfg_autopilot" / "runtime" / "autopilot.py"
    tag = sys.implementation.cache_tag
    assert list(prefix.rglob(f"autopilot.{tag}.pyc")), (tmp_path / "warm.log").read_text()
    # numba's lazily imported modules (loaded with the cached kernels) are in it too: without them
    # every controller compiled ~70 of numba's modules from source at start-up (~0.8 CPU s each)
    assert [p for p in prefix.rglob(f"*.{tag}.pyc") if "numba" in p.parts and "np" in p.parts], "numba.np not cached"
    # nothing stale: no second warm-up child
    assert launcher._bytecode_cache_env(sys.executable, tmp_path / "warm2.log") is not None
    assert not (tmp_path / "warm2.log").exists()
    # a module of the manifest newer than its byte-code (or without any) -> warmed again
    manifest = next(prefix.glob("manifest-*.txt"))
    src = tmp_path / "newer.py"
    src.write_text("")
    manifest.write_text(manifest.read_text() + f"\n{src}\t{tmp_path / 'no.pyc'}")
    warmed = []
    monkeypatch.setattr(launcher.subprocess, "run", lambda argv, **kw: warmed.append(argv))
    assert launcher._bytecode_cache_env(sys.executable, tmp_path / "warm3.log") is not None
    assert warmed and warmed[0][-1] == str(manifest)
    monkeypatch.undo()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    monkeypatch.delenv("PYTHONPYCACHEPREFIX", raising=False)
    os.chmod(prefix, 0o777)                               # a cache others could write to is never used
    assert launcher._bytecode_cache_env(sys.executable, tmp_path / "warm.log") is None
    assert runtime_src.exists()


def test_a_reused_results_folder_starts_clean_but_keeps_other_files(tmp_path):
    """Flying the same run again reuses its folder: the old controller logs (appended to, by
    design, across a controller's restarts) and results go, so the new flight is not merged
    with the old one (the t = 0 exchange was counted twice in comm_states); other files stay."""
    from mfg_swarm.launcher import clear_previous_run

    old = ["controllers/controller0.jsonl", "controllers/controller12.jsonl", "controllers/state3/checkpoint.pkl",
           "vehicles/vehicle0.tlog", "stderr/world.log",
           "metrics.json", "trajectories.npz", "fig3_trajectories.png", "flight.mcap", "flight.gif"]
    keep = ["notes.txt", "controllers/README", "vehicles/extra.bin"]
    for f in old + keep:
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_text("x")
    gone = clear_previous_run(tmp_path)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in gone) == sorted(old)
    assert all((tmp_path / f).exists() for f in keep) and not any((tmp_path / f).exists() for f in old)
    assert clear_previous_run(tmp_path / "missing") == []


def test_free_port_block_keeps_clear_of_the_ports_it_is_told_are_taken():
    # given every port but one block's worth in a small range promised to the launch already (free now, bound later):
    # the block picked avoids them all, and a range with no room left is refused with a clear error (2,000 random
    # tries over 35 starts: the one start that fits is missed with probability (34/35)^2000 < 1e-25)
    import pytest
    from mfg_swarm.launcher import LaunchError, _free_port_block
    lo, hi = 23000, 23040
    given = set(range(lo, hi)) - set(range(23017, 23022))
    for _ in range(20):
        udp, tcp = _free_port_block(3, 2, lo=lo, hi=hi, exclude=given, tries=2000)
        assert udp == [23017, 23018, 23019] and tcp == [23020, 23021]
    with pytest.raises(LaunchError, match="no block"):
        _free_port_block(3, 3, lo=lo, hi=hi, exclude=given, tries=50)
