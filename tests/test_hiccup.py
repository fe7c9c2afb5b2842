"""The host-noise meter behind the latency bench (mfg_swarm.hiccup): gap recording with a fake
clock, the job-exceedance probability against hand-worked cases and a brute-force reference."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mfg_swarm.hiccup import gap_summary, job_exceedance, record_gaps


def test_record_gaps_reports_every_jump_of_the_clock_over_the_threshold():
    # given a clock that ticks 10 us per read and jumps 3 ms at 1 ms and 0.15 ms at 2 ms
    t = [0.0]

    def clock():
        t[0] += 1e-5
        if abs(t[0] - 1e-3) < 5e-6:
            t[0] += 3e-3
        if abs(t[0] - 5e-3) < 5e-6:
            t[0] += 1.5e-4
        return t[0]

    g = record_gaps(0.01, threshold_s=2e-4, clock=clock, chunk_s=None)
    # then only the 3 ms jump is a gap, at ~1 ms, ~3.01 ms long
    assert g.shape == (1, 2)
    assert g[0, 0] == pytest.approx(1e-3, abs=2e-5) and g[0, 1] == pytest.approx(3.01e-3, abs=1e-6)


def test_chunks_are_laid_end_to_end_and_rest_between():
    # given a clock that ticks 10 us per read, 5 ms chunks with a rest (a sleep that moves the clock 100 ms)
    t = [0.0]
    slept = []

    def clock():
        t[0] += 1e-5
        return t[0]

    def sleep(s):
        slept.append(s)
        t[0] += 0.1

    g = record_gaps(0.02, clock=clock, chunk_s=0.005, rest_s=0.1, sleep=sleep)
    # then the rests are not gaps (they are between chunks) and there are three of them for four chunks
    assert g.shape == (0, 2) and slept == [0.1, 0.1, 0.1]


def test_no_gaps_means_no_exceedance_below_the_limit_and_certain_exceedance_above():
    none = np.zeros((0, 2))
    assert job_exceedance(none, 1.0, 4.9e-3, 5e-3) == 0.0
    assert job_exceedance(none, 1.0, 5.1e-3, 5e-3) == 1.0


def test_one_long_gap_delays_the_jobs_started_just_before_or_inside_it():
    # given one 10 ms gap at t = 1 s in 2 s, a 2 ms job and a 5 ms limit: the job ends late if it
    # starts in the 2 ms before the gap or in the first 7 ms of it: 9 ms of the 1.995 s of starts
    p = job_exceedance(np.array([[1.0, 0.01]]), 2.0, 2e-3, 5e-3, step_s=1e-5)
    assert p == pytest.approx(0.009 / 1.995, rel=2e-3)
    # a gap shorter than the slack (5 - 2 = 3 ms) never pushes the job over
    assert job_exceedance(np.array([[1.0, 0.0029]]), 2.0, 2e-3, 5e-3) == 0.0


def test_job_exceedance_matches_a_brute_force_walk_through_random_gaps():
    # given random gaps (seeded) and start times on a 0.1 ms grid, each job walked step by step
    rng = np.random.default_rng(4)
    dur, lim = 1.0, 5e-3
    starts_g = np.sort(rng.uniform(0, dur, 40))
    lens = rng.exponential(2e-3, 40)
    keep = np.concatenate([[True], starts_g[1:] > (starts_g[:-1] + lens[:-1])])     # no overlaps
    gaps = np.column_stack([starts_g[keep], lens[keep]])
    dt = 1e-5
    grid = np.arange(0.0, dur + 0.1, dt)
    running = np.ones(grid.size, dtype=bool)
    for s, ln in gaps:
        running[(grid >= s) & (grid < s + ln)] = False
    cum = np.concatenate([[0], np.cumsum(running)])
    for job in (1e-3, 2.5e-3, 4e-3):
        late = []
        for t in np.arange(0.0, dur - lim, 1e-3):
            i = int(round(t / dt))
            need = int(round(job / dt))
            j = np.searchsorted(cum, cum[i] + need)          # first grid index with that much run time
            late.append((j - i) * dt > lim + 1e-9)
        brute = np.mean(late)
        # then the closed form agrees to within the grid's resolution (a few start times of 995)
        assert job_exceedance(gaps, dur, job, lim, step_s=1e-3) == pytest.approx(brute, abs=4e-3)


def test_gap_summary_counts_by_length():
    s = gap_summary(np.array([[0.1, 0.0005], [0.2, 0.0015], [0.3, 0.006]]), 2.0)
    assert (s["gaps"], s["per_s_over_1ms"], s["per_s_over_2ms"], s["per_s_over_5ms"]) == (3, 1.0, 0.5, 0.5)
    assert s["max_ms"] == pytest.approx(6.0) and s["lost_fraction"] == pytest.approx(0.008 / 2.0)


def test_cli_prints_json_and_refuses_bad_arguments():
    p = subprocess.run([sys.executable, "-m", "mfg_swarm.hiccup", "--duration-s", "0.2"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert r["duration_s"] == 0.2 and set(r["job_exceedance"]) >= {"1", "2.5", "4.5"}
    assert all(0.0 <= v <= 1.0 for v in r["job_exceedance"].values())
    bad = subprocess.run([sys.executable, "-m", "mfg_swarm.hiccup", "--duration-s", "0.001"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "must exceed" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "mfg_swarm.hiccup", "--cpu", "4096"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "not available" in bad.stderr
