"""Finite-difference HJB / FPK / MFG solvers (mfg_autopilot.pde.solver) and the solved controllers
(mfg_autopilot.pde.control): convergence to the Riccati value, mass and positivity of the FPK,
the MFG fixed point, and the *-pde modes in the simulator."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.paper.model import lqr_riccati_axis
from mfg_autopilot.paper.params import PAPER, CostParams
from mfg_autopilot.pde.solver import (
    AxisGrid,
    AxisProblem,
    axis_problems,
    cfl_dt_s,
    deposit_cic,
    fpk_forward_step,
    interp_bilinear,
    solve_mfg,
    solve_stationary_hjb,
)
from mfg_autopilot.presets import make_controller
from mfg_swarm.results import load_trajectories

LQ_BOUND = 0.08      # relative max error of the finest grid on the inner region (measured 0.062)


def _lq_error(h: float) -> float:
    """Relative max error |psi - s^T P s| / max s^T P s on |x| <= 0.25, |v| <= 1 of the grid
    [-1, 1] x [-4, 4] (spacings h, 4h): the LQ part only (v_o = 0, no noise, kappa = 0,
    unconstrained a as in eq. 8, rho = 1e-4 so P_rho ~ P to 1e-4)."""
    c = CostParams()
    P = lqr_riccati_axis(c)
    prob = AxisProblem(c.c0_per_s, c.c1, c.c2, c.c3, v_o_m_s=0.0, sigma_m_s=0.0, kappa=0.0, acc_box_m_s2=None, rho_per_s=1e-4)
    g = AxisGrid.make(-1.0, 1.0, 4.0, h, 4.0 * h)
    st = solve_stationary_hjb(g, prob)
    assert st.policy_change < 1e-6, st.policy_change           # Howard converged
    X, V = g.mesh()
    exact = P[0, 0] * X**2 + 2 * P[0, 1] * X * V + P[1, 1] * V**2
    inner = (np.abs(X) <= 0.25) & (np.abs(V) <= 1.0)
    return float(np.max(np.abs(st.psi - exact)[inner]) / np.max(exact[inner]))


def test_lq_value_converges_to_riccati_as_grid_is_refined():
    # given the LQ part of the paper's cost, when the grid is refined twice,
    errs = [_lq_error(h) for h in (0.05, 0.025, 0.0125)]
    # then the error to the closed-form Riccati value shrinks (first order) and the finest is within the bound
    assert errs[1] < 0.75 * errs[0] and errs[2] < 0.75 * errs[1], errs
    assert errs[2] < LQ_BOUND, errs


def _paper_axis(dx=2.0, dv=0.5):
    c = PAPER.cost
    probs = axis_problems(c, np.array([150.0, 100.0]), 2.0 / np.sqrt(2.0))
    return c, probs[0], AxisGrid.make(-20.0, 170.0, 16.0, dx, dv)


def test_stationary_policy_of_paper_cost_points_home_and_respects_box():
    c, prob, g = _paper_axis()
    st = solve_stationary_hjb(g, prob)
    assert st.policy_change < 1e-6
    assert np.all(np.abs(st.a_m_s2) <= prob.acc_box_m_s2 + 1e-12)
    X, V = g.mesh()
    far = (X > 50) & (np.abs(V) < 2)
    assert np.all(st.a_m_s2[far] < 0)                             # accelerate towards the destination
    i0, j0 = np.argmin(np.abs(g.x_m)), np.argmin(np.abs(g.v_m_s))
    assert st.psi[i0, j0] == pytest.approx(st.psi.min(), rel=0, abs=np.ptp(st.psi) * 1e-3)


def test_fpk_conserves_mass_and_stays_nonnegative_under_cfl():
    c, prob, g = _paper_axis()
    st = solve_stationary_hjb(g, prob)
    rng = np.random.default_rng(1)
    m = deposit_cic(g, rng.normal(150.0, 3.0, 50), rng.normal(1.0, 0.3, 50))
    dt = cfl_dt_s(g, prob)
    assert m.sum() == pytest.approx(1.0, abs=1e-15)
    for _ in range(int(30.0 / dt)):                               # 30 s of flight under the solved policy
        m = fpk_forward_step(g, prob, m, st.a_m_s2, dt)
    assert abs(m.sum() - 1.0) < 1e-12
    assert m.min() >= 0.0
    xbar = m.sum(axis=1) @ g.x_m
    assert abs(xbar) < 5.0                                        # the mass has flown home (from 150 m)


def test_fpk_positivity_is_lost_beyond_cfl():
    # the CFL condition is what keeps m >= 0: 1.5 times the limiting step breaks it
    c, prob, g = _paper_axis()
    st = solve_stationary_hjb(g, prob)
    m = deposit_cic(g, np.array([100.0]), np.array([15.0]))      # fast mass: the largest rates
    dt = 1.5 * cfl_dt_s(g, prob, safety=1.0)
    lowest = 0.0
    for _ in range(20):
        m = fpk_forward_step(g, prob, m, st.a_m_s2, dt)
        lowest = min(lowest, m.min())
    assert lowest < -1e-3
    assert abs(m.sum() - 1.0) < 1e-9                              # mass is still conserved (conservative form)


def test_deposit_and_interpolation_are_consistent():
    g = AxisGrid.make(-5.0, 5.0, 3.0, 0.5, 0.25)
    x = np.array([-1.3, 0.2, 2.71]); v = np.array([0.1, -1.05, 2.0])
    m = deposit_cic(g, x, v)
    assert m.sum() == pytest.approx(1.0) and m.min() >= 0
    X, V = g.mesh()
    assert (m * X).sum() == pytest.approx(x.mean()) and (m * V).sum() == pytest.approx(v.mean())
    f = 2.0 * X - 3.0 * V + 0.5 * X * V + 1.0                      # bilinear: reproduced exactly
    assert interp_bilinear(g, f, x, v) == pytest.approx(2 * x - 3 * v + 0.5 * x * v + 1.0)


def test_mfg_fixed_point_keeps_mass_and_converges():
    c = PAPER.cost
    rng = np.random.default_rng(0)
    pos = np.stack(np.meshgrid(np.arange(3) * 1.41, np.arange(3) * 1.41), -1).reshape(-1, 2) + [60.0, 40.0]
    s0 = np.concatenate([pos, c.v_o + rng.normal(0, 0.2, (9, 2))], axis=1)
    probs = axis_problems(c, pos.mean(0), 2.0 / np.sqrt(2.0))
    grids = (AxisGrid.make(-15, 80, 12, 2.0, 0.5), AxisGrid.make(-15, 60, 12, 2.0, 0.5))
    sol = solve_mfg(grids, probs, c, s0, 1.0, 12, K=3)
    for ax in range(2):
        for mk in sol.m[ax]:
            assert abs(mk.sum() - 1.0) < 1e-12 and mk.min() >= 0.0
    assert sol.change[-1] < sol.change[0]                         # damped fixed point contracts
    xbar = [mk.sum(axis=1) @ grids[0].x_m for mk in sol.m[0]]
    assert xbar[-1] < xbar[0] - 30.0                              # the mean field flies home
    assert len(sol.dpsi_dv[0]) == 13 and np.all(np.isfinite(sol.dpsi_dv[0][0]))


def test_hjb_pde_neighbour_correction_aligns_velocity():
    # given two vehicles near home (far away the goal term saturates the action and swamps it),
    # when one hears a neighbour 0.3 m away flying 2 m/s faster in +y,
    ctrl = make_controller("hjb-pde", PAPER, np.zeros((2, 2)))
    own = np.array([[0.1, 0.0, 0.0, 0.0], [0.1, 20.0, 0.0, 0.0]])
    base = ctrl.step(Observation(0, 0.0, own)).acc_m_s2
    nb = Neighbours(np.array([[0.1, 0.3, 0.0, 2.0]]), np.array([0]))
    a = ctrl.step(Observation(1, 1.0, own, nb)).acc_m_s2
    # then its action turns towards the neighbour's velocity (Cucker-Smale alignment) and stays saturated
    assert a[0, 1] > base[0, 1] + 0.1
    assert a[1] == pytest.approx(base[1])
    assert np.all(np.linalg.norm(a, axis=1) <= PAPER.learner.acc_max_m_s2 + 1e-12)
    assert ctrl.weights()["w_H"].shape == (2, 54)


def _sim(tmp_path, *args):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "sim", "--out", str(out), "--no-progress", "--preset", "paper", *args],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads((out / "metrics.json").read_text()), load_trajectories(out / "trajectories.npz")


@pytest.mark.parametrize("args,comm", [(["--mode", "hjb-pde", "--range-m", "100"], 8.0 * 20),
                                       (["--mode", "mfg-pde"], 8.0)])
def test_pde_modes_fly_in_sim(tmp_path, args, comm):
    m, traj = _sim(tmp_path, "--n", "9", "--steps", "20", "--seed", "0", *args)
    assert m["comm_states_per_uav"] == comm
    a = np.linalg.norm(traj.acc_m_s2, axis=2)
    assert np.all(np.isfinite(traj.acc_m_s2)) and np.all(a <= 2.0 + 1e-6)
    assert np.mean(a[:10] > 2.0 - 1e-3) > 0.9                     # far from home the action is saturated
    d = np.linalg.norm(traj.pos_m - traj.dest_m[None], axis=2)
    assert d[-1].mean() < 0.2 * d[0].mean()                       # and it brings the swarm home


def test_bench_pde_smoke():
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1] / "bench"))
    from pde_bench import bench_pde

    from mfg_autopilot.pde.control import PDEParams
    r = bench_pde(n=4, steps=3, levels=((4.0, 1.0),), mfg_levels=1, inits=("lqr",),
                  pde_params=PDEParams(dx_m=4.0, dv_m_s=1.0, horizon_s=10.0), flights=False)
    assert set(r["distances"]) == {"hjb/lqr", "mfg/lqr"}
    for d in r["distances"].values():
        assert np.isfinite(d["value_rel_rms"]) and d["control_mean_m_s2"] >= 0
    modes = [t["mode"] for t in r["timing"]]
    assert modes == ["hjb-pde", "mfg-pde"]
    assert all(t["learned_s_per_decision"] > 0 and t["ratio_step"] > 0 for t in r["timing"])
