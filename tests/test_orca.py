"""The ``orca`` mode (mfg_autopilot/safety/orca.py): ORCA over the proximity sensor, no communication."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from mfg_autopilot.guidance.params import DEFAULT
from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.paper.params import PAPER
from mfg_autopilot.presets import MODES, make_controller
from mfg_autopilot.safety import kernels
from mfg_autopilot.safety.orca import OrcaController, orca_velocities_m_s, preferred_velocity_m_s, select_neighbours
from mfg_autopilot.safety.params import OrcaParams
from mfg_swarm.metrics import COLLISION_DISTANCE_M, collisions
from mfg_swarm.scenarios import Scenario, make_scenario
from mfg_swarm.sim import SimConfig, simulate

A_MAX = DEFAULT.learner.acc_max_m_s2


def _fly(sc: Scenario, steps: int, seed: int = 0):
    return simulate(SimConfig(sc, "orca", DEFAULT, seed=seed, steps=steps), progress=False)


def _snapshot(rng: np.random.Generator, n: int, box_m: float) -> tuple[np.ndarray, Neighbours]:
    """n random states in a box and every pair within the sensor range, both directions (exact states)."""
    states = np.concatenate([rng.uniform(-box_m, box_m, (n, 2)), rng.uniform(-4.0, 4.0, (n, 2))], axis=1)
    d = np.linalg.norm(states[:, None, 0:2] - states[None, :, 0:2], axis=2)
    owner, other = np.nonzero((d <= DEFAULT.backstop.sensor_range_m) & ~np.eye(n, dtype=bool))
    return states, Neighbours(states[other], owner, other)


def test_orca_is_a_mode_of_the_default_preset_only():
    assert "orca" in MODES
    ctrl = make_controller("orca", DEFAULT, np.zeros((3, 2)))
    assert isinstance(ctrl, OrcaController) and ctrl.mode == "orca" and ctrl.n == 3
    assert ctrl.uses_t0_exchange is False and ctrl.sensor_range_m == DEFAULT.backstop.sensor_range_m
    assert ctrl.weights()["w_H"].shape == (3, 1)
    with pytest.raises(ValueError, match="no controller for preset 'paper' in mode 'orca'"):
        make_controller("orca", PAPER, np.zeros((3, 2)))


def test_head_on_pair_avoids_and_both_arrive():
    """Given two vehicles 60 m apart flying to each other's start on one line (wind noise only breaks
    the symmetry), when flown, then they pass > 2 x 0.1 m apart and both arrive."""
    sc = Scenario("head-on", np.array([[-30.0, 0.0], [30.0, 0.0]]), np.array([[30.0, 0.0], [-30.0, 0.0]]),
                  np.array([0, 1]), np.zeros((2, 2)))
    traj, m = _fly(sc, steps=100)
    assert m["collision_pairs"] == 0 and m["min_pair_distance_m"] > 2 * COLLISION_DISTANCE_M, m["min_pair_distance_m"]
    assert m["arrived_fraction"] == 1.0 and m["arrival_time_s"] < 30.0
    assert m["comm_states_per_uav"] == 0.0


@pytest.mark.parametrize("n,seed", [(8, 0), (12, 1), (14, 2)])
def test_circle_to_antipodes_has_no_collided_pair(n, seed):
    """The classic reciprocal benchmark: N vehicles on a circle each fly to its antipode. (Measured: from
    N = 16 some seeds collide - the acceleration limit; docs/benchmarks.md, "ORCA baseline".)"""
    traj, m = _fly(make_scenario("circle", n, seed), steps=120, seed=seed)
    assert collisions(traj.pos_m)["collision_pairs"] == 0 and m["collision_pairs"] == 0
    assert m["arrived_fraction"] == 1.0


def test_acceleration_never_exceeds_the_cap():
    """Given a dense crowd (0.5 m grid flying to one point: ORCA's velocities are far out of one
    step's reach), then every commanded acceleration is within acc_max, in the bank's output and
    in the flown trajectory (float32 on the link)."""
    sc = make_scenario("dense", 36, 0)
    ctrl = make_controller("orca", DEFAULT, sc.destination_m)
    rng = np.random.default_rng(3)
    states = np.concatenate([sc.initial_pos_m, rng.uniform(-4.0, 4.0, (36, 2))], axis=1)
    d = np.linalg.norm(states[:, None, 0:2] - states[None, :, 0:2], axis=2)
    owner, other = np.nonzero((d <= 10.0) & ~np.eye(36, dtype=bool))
    info = ctrl.step(Observation(0, 0.0, states, None, Neighbours(states[other], owner, other)))
    nrm = np.linalg.norm(info.acc_m_s2, axis=1)
    assert np.all(nrm <= A_MAX * (1 + 1e-12)) and np.max(nrm) > 0.99 * A_MAX     # the cap is reached, not exceeded
    traj, _ = _fly(sc, steps=60)
    assert np.max(np.linalg.norm(traj.acc_m_s2, axis=2)) <= A_MAX * (1 + 1e-6)


@pytest.mark.parametrize("max_neighbours", [5, 30])
def test_bank_of_n_equals_n_banks_of_one(max_neighbours):
    """Each row's action depends only on its own state and what it senses: a bank holding every vehicle
    gives, row by row, exactly what n vehicle processes (banks of one, neighbours listed in another order)
    give - with and without the max_neighbours truncation."""
    rng = np.random.default_rng(18)
    n = 40
    states, sensed = _snapshot(rng, n, 12.0)
    dest = rng.uniform(-50.0, 50.0, (n, 2))
    preset = replace(DEFAULT, orca=OrcaParams(max_neighbours=max_neighbours))
    bank = make_controller("orca", preset, dest)
    a_bank = bank.step(Observation(0, 0.0, states, None, sensed)).acc_m_s2
    assert np.count_nonzero(sensed.counts(n)) == n                 # every row has neighbours: RVO2 ran for each
    assert np.any(sensed.counts(n) > max_neighbours) == (max_neighbours == 5)
    for i in range(n):
        mine = np.flatnonzero(sensed.owner == i)
        mine = mine[rng.permutation(mine.size)]
        one = make_controller("orca", preset, dest[i:i + 1])
        obs = Observation(0, 0.0, states[i:i + 1], None, Neighbours(sensed.states[mine], np.zeros(mine.size, np.int64),
                                                                    sensed.ids[mine]))
        np.testing.assert_array_equal(one.step(obs).acc_m_s2[0], a_bank[i])


def test_neighbour_selection_is_the_nearest_within_range_per_row():
    own = np.array([[0.0, 0.0, 0.0, 0.0], [100.0, 0.0, 0.0, 0.0]])
    st = np.array([[3.0, 0, 0, 0], [1.0, 0, 0, 0], [2.0, 0, 0, 0], [10.5, 0, 0, 0], [101.0, 0, 0, 0]])
    sensed = Neighbours(st, np.array([0, 0, 0, 0, 1]), np.array([5, 6, 7, 8, 9]))
    assert select_neighbours(own, sensed, 10.0, 2).tolist() == [1, 2, 4]     # row 0: the 2 nearest; 10.5 m is beyond
    assert select_neighbours(own, Neighbours.empty(), 10.0, 2).size == 0
    # no neighbour: ORCA's answer is the preferred velocity (capped at max_speed)
    v = preferred_velocity_m_s(own, np.array([[50.0, 0.0], [100.0, 0.5]]), 4.0, 0.5, 0.4)
    np.testing.assert_allclose(v, [[4.0, 0.0], [0.0, 0.2]])
    np.testing.assert_array_equal(orca_velocities_m_s(own, v, Neighbours.empty(), OrcaParams(), 0.5), v)


def test_sim_cli_flies_orca_without_communication(tmp_path):
    from mfg_swarm.cli import main

    out = tmp_path / "orca"
    assert main(["sim", "--mode", "orca", "--scenario", "crossing", "--n", "20", "--seed", "1", "--steps", "200",
                 "--out", str(out), "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["mode"] == "orca" and m["n"] == 20 and m["range_m"] is None
    assert m["comm_states_per_uav"] == 0.0
    assert m["collision_pairs"] == 0


def test_bad_parameters_are_clear_errors():
    for kw, msg in [(dict(radius_m=0.0), "radius_m"), (dict(time_horizon_s=-1.0), "time_horizon_s"),
                    (dict(max_speed_m_s=float("inf")), "max_speed_m_s"), (dict(max_neighbours=0), "max_neighbours"),
                    (dict(max_neighbours=2.5), "max_neighbours"), (dict(neighbour_dist_m=float("nan")), "neighbour_dist_m")]:
        with pytest.raises(ValueError, match=msg):
            OrcaParams(**kw)
    with pytest.raises(ValueError, match="must not exceed the proximity sensor's range"):
        OrcaController(DEFAULT, np.zeros((2, 2)), OrcaParams(neighbour_dist_m=20.0))
    with pytest.raises(ValueError, match="guidance and backstop"):
        OrcaController(PAPER, np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"\(n, 2\)"):
        OrcaController(DEFAULT, np.zeros(3))
    ctrl = OrcaController(replace(DEFAULT, orca=OrcaParams(radius_m=0.3)), np.zeros((2, 2)))
    assert ctrl.params.radius_m == 0.3
    with pytest.raises(ValueError, match=r"own_states must be \(2, 4\)"):
        ctrl.step(Observation(0, 0.0, np.zeros((3, 4))))


RVO2_TOL_M_S = 1e-4     # the stated agreement of the numba port with RVO2 (measured: bit-identical, 0.0)


def _random_bank(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, Neighbours]:
    """n rows far apart, each with 0-30 neighbours of its own within a random scale (0.3 m: overlapping discs, RVO2's
    collision branch and infeasible programmes; 10 m: mostly feasible), random velocities and preferred velocities
    (some beyond max_speed)."""
    own = np.concatenate([rng.uniform(-100.0, 100.0, (n, 2)) + 1000.0 * np.arange(n)[:, None],
                          rng.uniform(-4.0, 4.0, (n, 2))], axis=1)
    v_pref = rng.uniform(-5.0, 5.0, (n, 2))
    k = rng.integers(0, 31, n)
    owner = np.repeat(np.arange(n), k)
    scale = rng.choice([0.3, 1.0, 3.0, 10.0], n)[owner][:, None]
    rel = rng.uniform(-1.0, 1.0, (owner.size, 2)) * scale
    st = np.concatenate([own[owner, 0:2] + rel, rng.uniform(-4.0, 4.0, (owner.size, 2))], axis=1)
    perm = rng.permutation(owner.size)                      # sensed entries in no particular order
    return own, v_pref, Neighbours(st[perm], owner[perm], np.arange(owner.size)[perm] + n)


def test_numba_kernel_agrees_with_rvo2_on_random_cases():
    """Given 200 random banks of 1-12 rows (0-30 neighbours each, overlapping discs among them), when the numba port
    (kernels.orca_rows, RVO2's float32 arithmetic) and RVO2 itself (pyrvo, one simulator per row) compute ORCA's
    velocity, then they agree to RVO2_TOL_M_S on every row - and the cases reach the collision branch and
    linearProgram3 (infeasible programmes) many times."""
    pytest.importorskip("pyrvo")
    rng = np.random.default_rng(20261125)
    p = OrcaParams()
    worst, rows, exact, infeasible, collide = 0.0, 0, 0, 0, 0
    for _ in range(200):
        n = int(rng.integers(1, 13))
        own, v_pref, sensed = _random_bank(rng, n)
        a = orca_velocities_m_s(own, v_pref, sensed, p, 0.5)
        b = orca_velocities_m_s(own, v_pref, sensed, p, 0.5, backend="rvo2")
        diff = np.max(np.abs(a - b), axis=1)
        worst = max(worst, float(diff.max()))
        rows += n
        exact += int(np.count_nonzero(diff == 0.0))
        sel = select_neighbours(own, sensed, p.neighbour_dist_m, p.max_neighbours)
        owner = sensed.owner[sel]
        rel = sensed.states[sel, 0:2] - own[owner, 0:2]
        collide += int(np.count_nonzero(np.linalg.norm(rel, axis=1) <= 2 * p.radius_m))
        if sel.size:
            r = np.flatnonzero(np.bincount(owner, minlength=n))
            bounds = np.searchsorted(owner, np.r_[r, n])
            v, inf = kernels.orca_rows(rel, np.ascontiguousarray(sensed.states[sel, 2:4]), bounds,
                                       np.ascontiguousarray(own[r, 2:4]), np.ascontiguousarray(v_pref[r]), p.radius_m,
                                       p.time_horizon_s, 0.5, p.max_speed_m_s)
            np.testing.assert_array_equal(v, a[r])
            infeasible += int(np.count_nonzero(inf))
    assert worst <= RVO2_TOL_M_S, worst
    assert exact == rows, (exact, rows)              # measured: every row bit-identical (same float32 operations)
    assert infeasible >= 50 and collide >= 100, (infeasible, collide)


def test_numba_kernel_agrees_with_rvo2_on_simulated_snapshots():
    """Dense random snapshots (every pair within the sensor range, exact states): the bank's accelerations are those of
    the RVO2 backend."""
    pytest.importorskip("pyrvo")
    rng = np.random.default_rng(7)
    for box in (1.0, 4.0, 12.0):
        states, sensed = _snapshot(rng, 40, box)
        v_pref = rng.uniform(-4.0, 4.0, (40, 2))
        a = orca_velocities_m_s(states, v_pref, sensed, OrcaParams(), 0.5)
        b = orca_velocities_m_s(states, v_pref, sensed, OrcaParams(), 0.5, backend="rvo2")
        np.testing.assert_allclose(a, b, rtol=0, atol=RVO2_TOL_M_S)
    with pytest.raises(ValueError, match="backend"):
        orca_velocities_m_s(states, v_pref, sensed, OrcaParams(), 0.5, backend="cpp")


def _select_reference(own, sensed, neighbour_dist_m, max_neighbours):
    """select_neighbours as it was in numpy (lexsort), verbatim."""
    m = sensed.states.shape[0]
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    owner = np.asarray(sensed.owner, dtype=np.int64)
    d = sensed.states[:, 0:2] - own[owner, 0:2]
    d2 = d[:, 0] ** 2 + d[:, 1] ** 2
    cand = np.flatnonzero(d2 < neighbour_dist_m * neighbour_dist_m)
    if cand.size == 0:
        return cand
    ids = np.asarray(sensed.ids, dtype=np.int64)[cand] if sensed.ids is not None else np.zeros(cand.size, dtype=np.int64)
    order = cand[np.lexsort((cand, ids, d2[cand], owner[cand]))]
    ow = owner[order]
    start = np.flatnonzero(np.r_[True, ow[1:] != ow[:-1]])
    rank = np.arange(ow.size) - np.repeat(start, np.diff(np.r_[start, ow.size]))
    return order[rank < max_neighbours]


def test_compiled_neighbour_selection_equals_the_lexsort():
    """kernels.orca_select gives exactly the numpy lexsort's selection and order, ties included (integer grids: many
    equal distances), with and without vehicle ids, for max_neighbours 1, 3, 30."""
    rng = np.random.default_rng(11)
    for c in range(200):
        n, m = int(rng.integers(1, 40)), int(rng.integers(0, 400))
        own = rng.integers(-5, 5, (n, 4)).astype(float)
        sensed = Neighbours(rng.integers(-12, 12, (m, 4)).astype(float), rng.integers(0, n, m),
                            rng.integers(0, 20, m) if c % 2 else None)
        for k in (1, 3, 30):
            np.testing.assert_array_equal(select_neighbours(own, sensed, 10.0, k), _select_reference(own, sensed, 10.0, k))


def test_an_orca_step_compiles_nothing_after_the_warm_up():
    """Building the orca bank loads its kernels (orca.warm_up): its control steps compile no new signature."""
    code = """
import numpy as np
from numba.core.registry import CPUDispatcher
from mfg_autopilot.safety import kernels
from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.presets import make_controller, preset_by_name
from mfg_swarm.scenarios import make_scenario
p = preset_by_name("default"); n = 25; sc = make_scenario("dense", n)
c = make_controller("orca", p, sc.destination_m)
sigs = lambda: {k: len(v.signatures) for k, v in vars(kernels).items() if isinstance(v, CPUDispatcher)}
before = sigs()
rng = np.random.default_rng(0)
for k in range(5):
    s = np.concatenate([sc.initial_pos_m, rng.uniform(-2, 2, (n, 2))], axis=1).astype(np.float32).astype(float)
    s.setflags(write=False)
    d = np.linalg.norm(s[:, None, 0:2] - s[None, :, 0:2], axis=2)
    owner, other = np.nonzero((d <= 10.0) & ~np.eye(n, dtype=bool))
    c.step(Observation(k, 0.5 * k, s, None, Neighbours(s[other], owner.astype(np.int32), other)))
after = sigs()
print("new", sorted(k for k in after if after[k] != before.get(k, 0)))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().splitlines()[-1] == "new []"


@pytest.mark.parametrize("case", range(8))
def test_the_sensed_cutoff_keeps_every_action_bit_for_bit(case):
    """OrcaController.sensed_cutoff_m: the simulator's sensing restricted to the declared reach
    (spatial.pairs_within_reach, clip at the sensor range) gives the same accelerations, bit for bit,
    as every vehicle within the sensor range: crowds where hundreds are sensed and only the 30 nearest
    count, sparse vehicles with fewer than 30 in range, ties (integer grids, coincident vehicles),
    quantised sensed states (the ADS-B resolution), banks too small for a cutoff."""
    from mfg_swarm.sim import as_f32
    from mfg_swarm.spatial import pairs_within_reach
    from mock_vehicle.proximity import quantise_sensed_states, sensed_pairs, sensed_rows

    rng = np.random.default_rng(100 + case)
    n = [20, 31, 32, 200, 600, 600, 900, 400][case]
    if case in (4, 6):        # a tight crowd (0.4 m apart), a stream around it and some far away
        pos = np.concatenate([rng.normal(0.0, 2.0, (n // 2, 2)), rng.uniform(-25, 25, (n // 2 - 20, 2)),
                              rng.uniform(200, 300, (20, 2))])
    elif case == 5:           # integer grid: many equal distances, and coincident vehicles
        pos = rng.integers(-6, 6, (n, 2)).astype(float)
    elif case == 7:           # crowds at about the neighbour distance from each other
        pos = np.concatenate([rng.normal(0.0, 0.5, (n // 2, 2)), rng.normal(0.0, 0.5, (n // 2, 2)) + [9.9, 0.0]])
    else:
        pos = rng.uniform(-15.0, 15.0, (n, 2))
    obs = as_f32(np.concatenate([pos, rng.uniform(-4.0, 4.0, (n, 2))], axis=1))
    dest = rng.uniform(-50.0, 50.0, (n, 2))
    ctrl = OrcaController(DEFAULT, dest)
    r_s = DEFAULT.backstop.sensor_range_m

    def act(pairs):
        owner, other = sensed_rows(pairs)
        q = np.zeros_like(obs)
        seen = np.unique(other)
        q[seen] = quantise_sensed_states(obs[seen])
        return ctrl.step(Observation(0, 0.0, obs, None, Neighbours(q[other], owner, other))).acc_m_s2

    full = sensed_pairs(obs, r_s)
    reach = ctrl.sensed_cutoff_m(obs)
    if n <= ctrl.params.max_neighbours + 1:
        assert reach is None
        return
    cut = pairs_within_reach(None, obs[:, 0:2], reach, r_s, clip=True, vel=obs[:, 2:4])
    if case in (4, 6, 7):
        assert cut.shape[0] < 0.5 * full.shape[0]          # the cutoff does drop vehicles there
    np.testing.assert_array_equal(act(cut), act(full))
