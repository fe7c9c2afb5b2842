"""The self-consistent mean-field plan of the default MFG controller, and its pieces.

After the t = 0 exchange every UAV knows the N states s_j(0) and the N mission sites.
From these alone (deterministic code, same inputs in the same order, so every UAV - in
a bank of 1 or of N - gets bit-identical numbers) it computes:

1. Slots (the destination as a site): slot_j = site_j + (r_j(0) - centroid of j's group),
   a group being the UAVs that share a site.
2. The plan: N particles, m(0) = the exchanged states (Algorithm 4's m^[0](0)), moved by
   the noise-free model of eq. 9, ds = (A s + B (a + c0 v_o)) dt, with the *interacting*
   policy a_j = a_rep,j + sat(a_goal,j, a_plan_max - |a_rep,j|): the goal term (guidance to
   the slot) capped first, the pairwise closest-approach repulsion (the interaction cost,
   see :func:`repulsion_acc`) with priority. Each particle's action is held over the
   control period and integrated with the plant's Euler sub-steps, so a UAV that tracked
   its particle perfectly, without wind, would fly it exactly.
   Pairs are found with a k-d tree and a cutoff radius (O(N log N + pairs) per step).

Shapes: states (N, 4) [x_m, y_m, vx_m_s, vy_m_s]; accelerations (N, 2).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.params import GuidanceParams, RepulsionParams
from mfg_autopilot.paper.model import cap_norm
from mfg_autopilot.paper.params import CostParams

__all__ = ["slots_from_sites", "min_spacing_m", "goal_acc", "repulsion_acc", "combine_priority", "formation_goal_acc",
           "MeanFieldPlan"]


def slots_from_sites(pos0_m: np.ndarray, sites_m: np.ndarray) -> np.ndarray:
    """slot_j = site_j + r_j(0) - mean of r_k(0) over k with site_k == site_j. (N, 2)."""
    pos0 = np.asarray(pos0_m, dtype=float)
    sites = np.asarray(sites_m, dtype=float).reshape(pos0.shape)
    _, group = np.unique(sites, axis=0, return_inverse=True)
    group = group.reshape(-1)
    ng = int(group.max()) + 1
    cnt = np.bincount(group, minlength=ng).astype(float)
    cen = np.stack([np.bincount(group, pos0[:, d], ng) for d in range(2)], axis=1) / cnt[:, None]
    return sites + pos0 - cen[group]


def min_spacing_m(points_m: np.ndarray) -> float:
    """Smallest distance between two of the points (inf for fewer than 2)."""
    pts = np.asarray(points_m, dtype=float)
    if pts.shape[0] < 2:
        return float("inf")
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(np.min(d[:, 1]))


def goal_acc(s_rel: np.ndarray, g: GuidanceParams, cost: CostParams) -> np.ndarray:
    """Goal term towards the slot (the origin of s_rel), capped at a_goal_max. (n, 2).

    v_des = -r_hat * min(v_cruise, sqrt(2 a_brake |r|), k_r |r|); a = k_v (v_des - v) +
    c0 (v - v_o) (the model's drag and mean wind of eq. 9 are compensated)."""
    r, v = s_rel[:, 0:2], s_rel[:, 2:4]
    rho = np.linalg.norm(r, axis=1)
    speed = np.minimum(np.minimum(g.v_cruise_m_s, np.sqrt(2.0 * g.a_brake_m_s2 * rho)), g.k_r_per_s * rho)
    v_des = -r * (speed / np.maximum(rho, 1e-12))[:, None]
    a = g.k_v_per_s * (v_des - v) + cost.c0_per_s * (v - cost.v_o[None, :])
    return cap_norm(a, g.a_goal_max_m_s2)


def formation_goal_acc(x: np.ndarray, slots_m: np.ndarray, sites_m: np.ndarray, group: np.ndarray,
                       g: GuidanceParams, cost: CostParams, form_weight: np.ndarray | float = 1.0) -> np.ndarray:
    """Goal term of the plan, per group (UAVs sharing a site) as a virtual structure:
    the group centroid is guided to its site by :func:`goal_acc`'s velocity command, and
    each particle keeps its place in the formation with a PD on
    e_f = (r - slot) - (r_bar - site) and v - v_bar, scaled by form_weight (N,) in [0, 1]
    (the plan lowers it while a particle is being repelled, so that formations can
    deform to pass through each other). Capped at a_goal_max. (N, 2)."""
    ng = int(group.max()) + 1
    cnt = np.bincount(group, minlength=ng).astype(float)
    mean = np.stack([np.bincount(group, x[:, d], ng) for d in range(4)], axis=1) / cnt[:, None]   # (ng, 4)
    site_g = np.zeros((ng, 2))
    site_g[group] = sites_m
    rel_g = mean - np.concatenate([site_g, np.zeros_like(site_g)], axis=1)
    rho = np.linalg.norm(rel_g[:, 0:2], axis=1)
    speed = np.minimum(np.minimum(g.v_cruise_m_s, np.sqrt(2.0 * g.a_brake_m_s2 * rho)), g.k_r_per_s * rho)
    v_des_g = -rel_g[:, 0:2] * (speed / np.maximum(rho, 1e-12))[:, None]
    e_f = (x[:, 0:2] - slots_m) - rel_g[group, 0:2]
    e_fv = x[:, 2:4] - mean[group, 2:4]
    a_group = g.k_v_per_s * (v_des_g[group] - mean[group, 2:4]) + cost.c0_per_s * (x[:, 2:4] - cost.v_o[None, :])
    a_form = cap_norm(-(g.k_fp_per_s2 * e_f + g.k_fd_per_s * e_fv) * np.reshape(form_weight, (-1, 1)), g.a_goal_max_m_s2)
    return combine_priority(a_form, a_group, g.a_goal_max_m_s2)          # keeping formation first


def _pair_force(d: np.ndarray, u: np.ndarray, radius_m, rp: RepulsionParams) -> tuple[np.ndarray, np.ndarray]:
    """Force on the second member of each pair (the first gets its negative), and the
    predicted closest approach rho. d = r_j - r_i, u = v_j - v_i, (p, 2)."""
    uu = np.einsum("pd,pd->p", u, u)
    tau = np.clip(-np.einsum("pd,pd->p", d, u) / np.maximum(uu, 1e-12), 0.0, rp.horizon_s)
    c = d + tau[:, None] * u
    rho = np.linalg.norm(c, axis=1)
    un = np.sqrt(uu)
    perp = np.stack([-u[:, 1], u[:, 0]], axis=1) / np.maximum(un, 1e-12)[:, None]      # u rotated +90 deg
    fallback = np.where((un > 1e-9)[:, None], perp, np.array([[1.0, 0.0]]))          # coincident and co-moving: push along x
    n_hat = np.where((rho > 1e-6)[:, None], c / np.maximum(rho, 1e-12)[:, None], fallback)
    # minimal push: the relative acceleration that opens the closest approach to the radius
    # by tau*, 2 (R - rho) / tau*^2, shared by the two members, capped at gain
    mag = np.minimum(rp.gain_m_s2, rp.urgency * np.maximum(radius_m - rho, 0.0) / np.maximum(tau, rp.tau_min_s) ** 2)
    u_hat = u / np.maximum(un, 1e-12)[:, None]
    f = mag[:, None] * (n_hat + rp.keep_right * np.where((un > 1e-9)[:, None], perp, 0.0) - rp.brake * u_hat)
    return f, rho


def repulsion_acc(states: np.ndarray, pairs: np.ndarray, radius_m: float, rp: RepulsionParams,
                  group: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Interaction term of the plan: sum over pairs (i, j) of the closest-approach push,
    antisymmetric (i gets -f, j gets +f), capped at a_rep_max. states (N, 4), pairs (p, 2).
    Returns (a_rep (N, 2), |push from other groups' particles| (N,))."""
    n = states.shape[0]
    out = np.zeros((n, 2))
    inter = np.zeros(n)
    if pairs.size == 0:
        return out, inter
    d, u = states[pairs[:, 1], 0:2] - states[pairs[:, 0], 0:2], states[pairs[:, 1], 2:4] - states[pairs[:, 0], 2:4]
    # exact pruning: |d + tau u| >= |d| - horizon |u| (0 <= tau <= horizon), so a pair with
    # |d| > R + horizon |u| (+ 1 um against rounding) has rho >= R and exactly zero force; its
    # terms (+-0.0) would not change the sums, and the kept pairs stay in their order
    keep = np.sqrt(np.einsum("pd,pd->p", d, d)) <= radius_m + rp.horizon_s * np.sqrt(np.einsum("pd,pd->p", u, u)) + 1e-6
    if not np.any(keep):
        return cap_norm(out, rp.a_rep_max_m_s2), inter
    pairs, d, u = pairs[keep], d[keep], u[keep]
    i, j = pairs[:, 0], pairs[:, 1]
    f, _ = _pair_force(d, u, radius_m, rp)
    for dim in range(2):
        out[:, dim] = np.bincount(j, f[:, dim], n) - np.bincount(i, f[:, dim], n)
    if group is not None:
        fn = np.linalg.norm(f, axis=1) * (group[i] != group[j])
        inter = np.bincount(i, fn, n) + np.bincount(j, fn, n)
    return cap_norm(out, rp.a_rep_max_m_s2), inter


def repulsion_from_neighbours(own: np.ndarray, nb_states: np.ndarray, owner: np.ndarray, radius_m,
                              rp: RepulsionParams) -> np.ndarray:
    """Per bank row: the push from the neighbour states it holds (HJB_d: heard; backstop:
    sensed). own (n, 4); nb_states (m, 4) owned by rows owner (m,). radius_m scalar or (n,)."""
    n = own.shape[0]
    out = np.zeros((n, 2))
    if nb_states.shape[0] == 0:
        return out
    rad = np.broadcast_to(np.asarray(radius_m, dtype=float), (n,))[owner]
    d, u = nb_states[:, 0:2] - own[owner, 0:2], nb_states[:, 2:4] - own[owner, 2:4]
    # exact pruning (as in repulsion_acc): rho >= |d| - horizon |u|, so a pair with |d| > R + horizon |u|
    # (+ 1 um against rounding) has exactly zero force; its +-0.0 terms cannot change the bincount sums
    keep = np.sqrt(np.einsum("pd,pd->p", d, d)) <= rad + rp.horizon_s * np.sqrt(np.einsum("pd,pd->p", u, u)) + 1e-6
    if not np.all(keep):
        d, u, rad, owner = d[keep], u[keep], rad[keep], owner[keep]
    f, _ = _pair_force(d, u, rad, rp)
    for dim in range(2):
        out[:, dim] = -np.bincount(owner, f[:, dim], n)
    return cap_norm(out, rp.a_rep_max_m_s2)


def combine_priority(a_rep: np.ndarray, a_goal: np.ndarray, a_max_m_s2: float) -> np.ndarray:
    """Priority saturation: a = a_rep + sat(a_goal, a_max - |a_rep|) (SPEC 7: capping the
    sum instead lets the goal term swamp the repulsion)."""
    room = np.maximum(a_max_m_s2 - np.linalg.norm(a_rep, axis=1), 0.0)
    return cap_norm(a_rep + cap_norm(a_goal, room), a_max_m_s2)


def euler_substeps(states: np.ndarray, acc: np.ndarray, dt_s: float, cost: CostParams, physics_dt_s: float = 0.1) -> np.ndarray:
    """Noise-free eq. 9 over dt_s with acc held, in the plant's Euler sub-steps (<= physics_dt_s)."""
    k = max(1, int(np.ceil(dt_s / physics_dt_s - 1e-9)))
    h = dt_s / k
    x = states
    for _ in range(k):
        v = x[:, 2:4]
        x = np.concatenate([x[:, 0:2] + v * h, v + (acc - cost.c0_per_s * (v - cost.v_o[None, :])) * h], axis=1)
    return x


class MeanFieldPlan:
    """The interacting N-particle plan computed from the t = 0 exchange (module docstring).

    ``advance()`` computes step k's action and moves the particles to step k+1; the plan is
    computed lazily, one control period at a time, so a UAV process pays O(N log N) per step.
    """

    def __init__(self, exchanged_states: np.ndarray, sites_m: np.ndarray, dt_s: float, cost: CostParams,
                 guidance: GuidanceParams, repulsion: RepulsionParams, use_slots: bool = True,
                 use_repulsion: bool = True) -> None:
        S0 = np.asarray(exchanged_states, dtype=float)
        if S0.ndim != 2 or S0.shape[1] != 4 or not np.all(np.isfinite(S0)):
            raise ValueError(f"exchanged_states must be a finite (N, 4) array, got {S0.shape}")
        self.N = S0.shape[0]
        sites = np.asarray(sites_m, dtype=float).reshape(self.N, 2)
        self.slots_m = slots_from_sites(S0[:, 0:2], sites) if use_slots else sites.copy()
        self.sites_m = sites
        _, grp = np.unique(sites, axis=0, return_inverse=True)
        self.group = grp.reshape(-1)
        spacing = min(min_spacing_m(self.slots_m), min_spacing_m(S0[:, 0:2]))
        self.spacing_m = float(spacing)          # smallest slot / start spacing
        self.radius_m = float(min(repulsion.radius_m, repulsion.slot_fraction * spacing))
        self.dt_s, self.cost, self.g, self.rp = float(dt_s), cost, guidance, repulsion
        self.use_repulsion, self.use_slots = use_repulsion, use_slots
        self.k = 0
        self.states = S0.copy()                  # plan states at step k, (N, 4)
        self.acc = None                          # plan action over [t_k, t_k+1), (N, 2)
        self.rep_active = np.zeros(self.N, dtype=bool)

    def _pairs(self, x: np.ndarray) -> np.ndarray:
        vmax = float(np.max(np.linalg.norm(x[:, 2:4], axis=1))) if self.N else 0.0
        cutoff = self.radius_m + 2.0 * vmax * self.rp.horizon_s
        if self.N:
            # tighter, still exact: |v_j - v_i| <= 2 max_k |v_k - c| for any c (the velocity box's centre), and
            # repulsion_acc keeps only |d| <= R + horizon |v_j - v_i| + 1e-6; a swarm flying together has
            # a small velocity spread, so this lists far fewer pairs than 2 max|v| (the same pairs are kept)
            c = 0.5 * (x[:, 2:4].min(axis=0) + x[:, 2:4].max(axis=0))
            spread = float(np.max(np.linalg.norm(x[:, 2:4] - c[None, :], axis=1)))
            cutoff = min(cutoff, self.radius_m + 2.0 * spread * self.rp.horizon_s + 2e-6)
        return cKDTree(x[:, 0:2]).query_pairs(cutoff, output_type="ndarray")

    def action(self) -> np.ndarray:
        """The plan's action at the current step k (computed once), (N, 2)."""
        if self.acc is None:
            x = self.states
            if self.use_repulsion and self.N > 1:
                a_rep, inter = repulsion_acc(x, self._pairs(x), self.radius_m, self.rp, self.group)
            else:
                a_rep, inter = np.zeros((self.N, 2)), np.zeros(self.N)
            if self.use_slots:
                # formation keeping yields to conflicts with *other* groups (formations must
                # deform to pass through each other); within a group it stays in force
                w_form = 1.0 / (1.0 + inter / self.rp.form_yield_m_s2)
                a_goal = formation_goal_acc(x, self.slots_m, self.sites_m, self.group, self.g, self.cost, w_form)
            else:
                a_goal = goal_acc(x - np.concatenate([self.slots_m, np.zeros_like(self.slots_m)], axis=1), self.g, self.cost)
            self.rep_active = np.linalg.norm(a_rep, axis=1) > 0
            self.acc = combine_priority(a_rep, a_goal, self.rp.a_plan_max_m_s2)
        return self.acc

    def advance(self) -> None:
        """Move the particles one control period with the held plan action."""
        a = self.action()
        self.states = euler_substeps(self.states, a, self.dt_s, self.cost)
        self.acc = None
        self.k += 1
