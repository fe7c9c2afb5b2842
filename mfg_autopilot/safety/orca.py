"""The ``orca`` mode: optimal reciprocal collision avoidance as a baseline controller bank.

ORCA (J. van den Berg, S. J. Guy, M. Lin, D. Manocha, *Reciprocal n-Body Collision Avoidance*,
ISRR 2009 / STAR 2011), computed by the original RVO2 library through its Python bindings
(``pyrvo``; the only module of the project that imports it). Communication-free: each vehicle
uses only its own observed state and what its onboard proximity sensor sees
(``Observation.sensed``, the same sensor and range, ``preset.backstop.sensor_range_m``, as the
default preset's backstop). No t = 0 exchange, no gossip: the communication metric is 0.

Per control step t_k, for each bank row i (own state s_i = [r_i, v_i]):

1. preferred velocity towards the own destination d_i (the default guidance's braking profile,
   ``guidance.planner.goal_acc``):
       v_pref = -rho_hat * min(v_cruise, sqrt(2 a_brake rho), k_r rho),   rho = r_i - d_i;
2. neighbours: the sensed vehicles closer than ``OrcaParams.neighbour_dist_m``, the
   ``max_neighbours`` nearest (ties by vehicle id, then sensor order) - RVO2's own rule,
   applied here so that each row's set is fixed before RVO2 sees it;
3. v_new = ORCA's velocity: the one closest to v_pref within |v| <= max_speed and the
   half-planes ORCA_ij^tau of those neighbours (their sensed positions and velocities; each
   vehicle a disc of ``radius_m``; time horizon tau; RVO2's 2-D linear programme);
4. the acceleration that reaches v_new in one control period under the model of eq. 9
   (``paper/model.py``: dv/dt = a - c0 (v - v_o)):
       a = (v_new - v_i) / dt + c0 (v_i - v_o),   capped at |a| <= learner.acc_max_m_s2.

ORCA assumes a vehicle takes any velocity up to max_speed at once; ours change velocity by at
most acc_max dt per step (1 m/s with the default preset), so ORCA's guarantee does not carry
over: the radius (0.2 m per vehicle against the 0.1 m collision distance) is the margin, and the
measured separations are in docs/benchmarks.md ("ORCA baseline").

Destinations: each vehicle flies to its own mission destination (``destination_site_m``). ORCA
has no t = 0 exchange, so it has no slot rule: the default controller's slot (site + own start
offset from the centroid of the group sharing the site, ``guidance.planner.slots_from_sites``)
needs every group member's start position, which only communication gives (the sensor sees 10 m,
a group spans more). When a group shares one site point, ORCA crowds its vehicles around that
point (reciprocal avoidance keeps them ``2 radius_m`` apart, so they cannot all be within the
1 m arrival tolerance); per-vehicle destinations (``circle``, or a mission with one site per
vehicle) do not have that limitation.

Exactness of the bank: row i's velocity is RVO2's velocity for an agent at the origin holding only the
own vehicle and its selected neighbours (at their positions relative to it), so a bank of n rows
gives, row by row, the same numbers as n banks of one (``tests/test_orca.py``). One RVO2 simulator
for the whole bank would not: RVO2 stores positions in float32 (1e-5 m at 100 m), a simulator shared
by every vehicle would put each at its own observed state where its neighbours sense a quantised
one, and RVO2 selects neighbours from everything it holds. Rows that sense no neighbour skip the
computation: with no half-plane the linear programme's answer is v_pref capped at max_speed.

Two backends compute it (``orca_velocities_m_s(..., backend=)``). "numba" (the default):
``kernels.orca_rows``, a line-by-line port of RVO2's Agent::computeNewVelocity (the agent ORCA lines
with the collision case, cut-off circle and legs; linearProgram1/2/3 with RVO2's RVO_EPSILON and sign
conventions; the max-speed disc) in RVO2's own float32 arithmetic, all rows in one call; the
neighbour selection is compiled too (``kernels.orca_select``). "rvo2": RVO2 itself through pyrvo, a
simulator built per row and step (never reused: RVO2's ``clearAgents`` leaves dangling agent pointers
in its k-d tree, RVOSimulator.cc, KdTree::buildAgentTree) - the reference. Agreement measured
2026-11-25: bit-identical on every row of 200 random banks (1-12 rows, 0-30 neighbours, overlapping
discs, infeasible programmes: the test states 1e-4 m/s) and 3,000 single-row cases; ``sim --scenario
swap4 --n 1000 --mode orca --steps 400 --seed 1`` gives bit-identical trajectories with either
backend (2370 collided pairs, min separation 8.2e-05 m), 45 s wall with "rvo2", 14 s with "numba".
At N = 10,000 (same command) 590 s wall with "numba" (not finished in 29 min with "rvo2"), most of
it the simulator's sensing of ORCA's crowds (up to 17 million sensed pairs a step); since
2026-11-25 55 s (``wall_s``), bit-identical: the bank declares ``sensed_cutoff_m`` (only a row's
``max_neighbours`` nearest can change its action, so the simulator lists ~600,000 pairs instead) and
the simulator builds the sorted sensed rows without a sort (docs/benchmarks.md, "Eighth round").

Shapes: own states (n, 4) [x_m, y_m, vx_m_s, vy_m_s]; velocities and accelerations (n, 2).
"""

from __future__ import annotations

import numpy as np

from mfg_autopilot.interface import Neighbours, Observation, StepInfo
from mfg_autopilot.paper.model import cap_norm
from mfg_autopilot.paper.params import Preset
from mfg_autopilot.safety import kernels
from mfg_autopilot.safety.params import OrcaParams

__all__ = ["OrcaController", "preferred_velocity_m_s", "select_neighbours", "orca_velocities_m_s", "warm_up"]


def _pyrvo():
    try:
        import pyrvo
    except ImportError as e:        # pragma: no cover - ./dev installs it
        raise ImportError("the orca mode needs pyrvo (RVO2's bindings): ./dev installs it, "
                          "or pip install --no-deps pyrvo==0.4.3") from e
    return pyrvo


def preferred_velocity_m_s(own: np.ndarray, dest_m: np.ndarray, v_cruise_m_s: float, a_brake_m_s2: float,
                           k_r_per_s: float) -> np.ndarray:
    """v_pref (n, 2) towards dest_m (n, 2): -rho_hat min(v_cruise, sqrt(2 a_brake rho), k_r rho)
    with rho = r - dest (the default guidance's profile, guidance.planner.goal_acc)."""
    r = own[:, 0:2] - dest_m
    rho = np.linalg.norm(r, axis=1)
    speed = np.minimum(np.minimum(v_cruise_m_s, np.sqrt(2.0 * a_brake_m_s2 * rho)), k_r_per_s * rho)
    return -r * (speed / np.maximum(rho, 1e-12))[:, None]


def select_neighbours(own: np.ndarray, sensed: Neighbours, neighbour_dist_m: float, max_neighbours: int) -> np.ndarray:
    """Indices into ``sensed`` of each row's ORCA neighbours, grouped by owner row and, within a row,
    nearest first: the sensed vehicles with |r_j - r_i| < neighbour_dist_m, at most max_neighbours
    per row, ties broken by vehicle id (if given) then by position in ``sensed`` (m',)."""
    m = sensed.states.shape[0]
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    owner = np.ascontiguousarray(sensed.owner, dtype=np.int64)
    ids = np.ascontiguousarray(sensed.ids, dtype=np.int64) if sensed.ids is not None else np.zeros(m, dtype=np.int64)
    n = own.shape[0]
    if owner.min() < 0 or owner.max() >= n:
        raise ValueError(f"sensed.owner must index the {n} own rows, got values in [{owner.min()}, {owner.max()}]")
    # one compiled pass (kernels.orca_select): the same order as np.lexsort((index, ids, d2, owner)) cut at max_neighbours
    # whole (., 4) state arrays (the kernel reads columns 0-1): no copy of the m sensed positions
    return kernels.orca_select(np.array(own, dtype=float), np.ascontiguousarray(sensed.states, dtype=float),
                               owner, ids,
                               n, float(neighbour_dist_m * neighbour_dist_m),
                               int(max_neighbours))


def orca_velocities_m_s(own: np.ndarray, v_pref_m_s: np.ndarray, sensed: Neighbours, p: OrcaParams,
                        dt_s: float, backend: str = "numba") -> np.ndarray:
    """ORCA's new velocity of each row (n, 2) (steps 2 and 3 of the module docstring): RVO2's velocity computation on
    the own vehicle at the origin and its selected neighbours relative to it. backend "numba": the compiled port of it
    (``kernels.orca_rows``, RVO2's float32 arithmetic, all rows in one call); "rvo2": RVO2 itself through pyrvo, one
    simulator per row (the reference; ~100x slower)."""
    if backend not in ("numba", "rvo2"):
        raise ValueError(f"backend must be 'numba' or 'rvo2', got {backend!r}")
    n = own.shape[0]
    v_new = cap_norm(np.asarray(v_pref_m_s, dtype=float), p.max_speed_m_s)     # no neighbour: the LP's answer
    sel = select_neighbours(own, sensed, p.neighbour_dist_m, p.max_neighbours)
    if sel.size == 0:
        return v_new
    owner = np.asarray(sensed.owner, dtype=np.int64)[sel]
    chosen = np.take(sensed.states, sel, axis=0)       # = sensed.states[sel]: np.take copies rows several times faster
    rel = chosen[:, 0:2] - np.take(own, owner, axis=0)[:, 0:2]
    vel = chosen[:, 2:4]
    rows = np.flatnonzero(np.bincount(owner, minlength=n))
    bounds = np.searchsorted(owner, np.r_[rows, n])
    if backend == "numba":
        v_new[rows], _ = kernels.orca_rows(np.ascontiguousarray(rel, dtype=float), np.ascontiguousarray(vel, dtype=float),
                                        np.ascontiguousarray(bounds, dtype=np.int64),
                                        np.ascontiguousarray(own[rows, 2:4], dtype=float),
                                        np.ascontiguousarray(np.asarray(v_pref_m_s, dtype=float)[rows]),
                                        float(p.radius_m), float(p.time_horizon_s), float(dt_s), float(p.max_speed_m_s))
        return v_new
    pyrvo = _pyrvo()
    rel = rel.tolist()
    vel = vel.tolist()
    # the own agent keeps every listed neighbour (neighborDist well beyond neighbour_dist_m, as RVO2 compares float32
    # squares; maxNeighbors = the row's count); the neighbour agents search none (their own velocities are not used)
    nd, tau, r, vmax = p.neighbour_dist_m + 1.0, p.time_horizon_s, p.radius_m, p.max_speed_m_s
    for k, i in enumerate(rows):
        lo, hi = int(bounds[k]), int(bounds[k + 1])
        sim = pyrvo.RVOSimulator()
        sim.set_time_step(dt_s)
        sim.add_agent((0.0, 0.0), nd, hi - lo, tau, tau, r, vmax, (float(own[i, 2]), float(own[i, 3])))
        for j in range(lo, hi):
            sim.add_agent(rel[j], 0.0, 0, tau, tau, r, vmax, vel[j])
        sim.set_agent_pref_velocity(0, (float(v_pref_m_s[i, 0]), float(v_pref_m_s[i, 1])))
        sim.do_step()
        v_new[i] = sim.get_agent_velocity(0).to_tuple()
    return v_new


def warm_up() -> None:
    """Load (or, on a cold cache, compile) the ORCA kernel through :func:`orca_velocities_m_s`, with the argument types of
    a control step, so that the first control step does not pay for it."""
    own = np.array([[0.0, 0.0, 1.0, 0.0], [3.0, 0.0, -1.0, 0.0]])
    sensed = Neighbours(own[::-1].copy(), np.array([0, 1]), np.array([1, 0]))
    orca_velocities_m_s(own, np.array([[1.0, 0.0], [-1.0, 0.0]]), sensed, OrcaParams(), 0.5)
    states = sensed.states.copy()
    states.setflags(write=False)            # sensed states passed through uncopied may be read-only (another signature)
    orca_velocities_m_s(own, np.array([[1.0, 0.0], [-1.0, 0.0]]), Neighbours(states, sensed.owner, sensed.ids),
                        OrcaParams(), 0.5)


class OrcaController:
    """A bank of n ORCA controllers (interface.Controller; module docstring). Built by
    ``presets.make_controller("orca", preset, destination_site_m)`` from a preset with ``guidance``
    (cruise speed, braking), ``backstop`` (sensor range) and ``orca`` (:class:`OrcaParams`)
    parameters - the ``default`` preset."""

    mode = "orca"
    uses_t0_exchange = False

    def __init__(self, preset: Preset, destination_site_m: np.ndarray, params: OrcaParams | None = None) -> None:
        missing = [k for k in ("guidance", "backstop") if not hasattr(preset, k)]
        if missing:
            raise ValueError(f"the orca controller needs a preset with {' and '.join(missing)} parameters "
                             f"(the default preset), got {getattr(preset, 'name', preset)!r}")
        p = params if params is not None else getattr(preset, "orca", OrcaParams())
        if not isinstance(p, OrcaParams):
            raise ValueError(f"params must be OrcaParams, got {type(p).__name__}")
        sensor_range_m = float(preset.backstop.sensor_range_m)
        if p.neighbour_dist_m > sensor_range_m:
            raise ValueError(f"OrcaParams.neighbour_dist_m ({p.neighbour_dist_m} m) must not exceed the proximity sensor's "
                             f"range ({sensor_range_m} m): ORCA sees only sensed vehicles")
        if not (preset.dt_s > 0 and np.isfinite(preset.dt_s)):
            raise ValueError(f"the preset's dt_s must be finite and > 0, got {preset.dt_s}")
        dest = np.asarray(destination_site_m, dtype=float)
        if dest.ndim != 2 or dest.shape[1] != 2 or dest.shape[0] < 1 or not np.all(np.isfinite(dest)):
            raise ValueError(f"destination_site_m must be a finite (n, 2) array with n >= 1, got shape {dest.shape}")
        self.preset = preset
        self.params = p
        self.sensor_range_m = sensor_range_m       # the simulator and the runtime deliver Observation.sensed within it
        self._dest = dest.copy()
        self._w = np.zeros((self._dest.shape[0], 1))
        self.backstop_active = np.zeros(self.n, dtype=bool)
        warm_up()                           # load the compiled ORCA kernels now, not in the first control step

    @property
    def n(self) -> int:
        return self._dest.shape[0]

    @property
    def destinations_m(self) -> np.ndarray:
        """(n, 2) each row's mission destination (no slot rule: module docstring)."""
        return self._dest

    _SENSED_POS_MARGIN_M = 0.05
    """Bound on how far a sensed position may lie from the true one: the proximity sensor's ADS-B
    resolution (1e-7 deg: <= 0.0056 m north, 0.0038 m east, half a step each way), with room."""

    def sensed_cutoff_m(self, states: np.ndarray, sensed_states: np.ndarray | None = None) -> tuple[float, np.ndarray] | None:
        """For a bank holding every vehicle (observed states (N, 4)): the reach (base_m, extra_m (N,))
        (``interface.Controller``): a sensed vehicle j can change row i's action only if
        |r_j - r_i| <= base + extra_i + extra_j, so a simulator may deliver only those (None: all within
        the sensor range). Row i uses only its ``max_neighbours`` nearest sensed vehicles within
        ``neighbour_dist_m`` (select_neighbours). With R_i the true distance to its max_neighbours-th nearest
        other vehicle (capped at neighbour_dist_m) and e the position margin: if R_i + e < neighbour_dist_m,
        those max_neighbours vehicles are sensed within R_i + e, so every selected j is sensed within
        R_i + e and truly within R_i + 2 e; otherwise a selected j is truly within neighbour_dist_m + e
        <= R_i + 2 e as well. Hence base = 2 e, extra_i = R_i: the selected sets, and the actions, are
        those of the full sensed set bit for bit (the selection's order is a total order on (distance, id),
        which any superset of the selected vehicles reproduces)."""
        states = np.asarray(states, dtype=float)
        n, k = states.shape[0], self.params.max_neighbours
        if n <= k + 1:
            return None
        from scipy.spatial import cKDTree       # here: only a simulator asks for a reach
        pos = np.ascontiguousarray(states[:, 0:2])
        nd = float(self.params.neighbour_dist_m)
        # the (k + 1)-th nearest point, the own vehicle included (at distance 0, among the first whatever the ties)
        d, _ = cKDTree(pos).query(pos, k=[k + 1], distance_upper_bound=nd)
        extra = np.minimum(d[:, 0], nd)          # inf (fewer than k within nd) -> nd
        return 2.0 * self._SENSED_POS_MARGIN_M, extra

    def exchange_t0(self, states, ids, own_index, sites_m) -> None:
        """Not used: ORCA exchanges nothing (``uses_t0_exchange`` is False)."""

    def step(self, obs: Observation) -> StepInfo:
        """Steps 1-4 of the module docstring for every row of the bank."""
        own = np.asarray(obs.own_states, dtype=float)
        if own.shape != (self.n, 4):
            raise ValueError(f"own_states must be ({self.n}, 4), got {own.shape}")
        g, cost, dt = self.preset.guidance, self.preset.cost, self.preset.dt_s
        v_pref = preferred_velocity_m_s(own, self._dest, g.v_cruise_m_s, g.a_brake_m_s2, g.k_r_per_s)
        sensed = obs.sensed if obs.sensed is not None else Neighbours.empty()
        v_new = orca_velocities_m_s(own, v_pref, sensed, self.params, dt)
        v = own[:, 2:4]
        a = (v_new - v) / dt + cost.c0_per_s * (v - cost.v_o[None, :])
        a = cap_norm(a, self.preset.learner.acc_max_m_s2)
        z = np.zeros(self.n, dtype=np.int64)
        return StepInfo(a, z, np.zeros(self.n, dtype=bool), np.zeros(self.n), z)

    def weights(self) -> dict[str, np.ndarray]:
        """Nothing is learned: one zero column per row (the simulator logs row 0's)."""
        return {"w_H": self._w}
