"""Mission scenarios: where the UAVs start and where each one is going.

- ``paper`` is Sec. V: N UAVs on a square grid with sqrt(2) m spacing centred at
  (150, 100) m, all flying to the origin.
- ``crossing``: two groups (N/2 and N - N/2) on sqrt(2) m grids centred at (-60, 0) and
  (60, 0) m; each group's site is the other's centre, so they swap sides through each other.
- ``dense``: the paper's grid with spacing 0.5 m, packed on a pad: every UAV starts *at rest* (a hover
  hold, or on the ground), not at its own wind velocity as the paper's airborne start does. Independent
  wind-drawn start velocities 0.5 m apart are a conflict no controller can undo: at N = 1,000 the worst
  neighbour pair closes at 1.3 m/s at t = 0, and even both braking at the 2 m/s^2 airframe limit from the
  first instant leaves them ~0.23 m apart, below half the spacing (docs/default_controller.md).
- ``swap4``: four groups of about N/4 on sqrt(2) m grids at the compass points, each flying to the
  opposite side: all four streams meet in the middle.
- ``circle``: N vehicles on a circle (neighbours sqrt(2) m apart, so the radius grows with N), each
  flying to its antipode (each vehicle its own group): the classic reciprocal-avoidance benchmark.
- ``merge``: k sources (k = 2..6 from the seed) at distinct bearings, 80 m and more out, converging
  on one site area: each group's slot block on the side of the common centre facing its source.
- ``random``: random starts in a box (at least ``RANDOM_MIN_SPACING_M`` apart, Poisson-disc
  rejection on a grid), 2..8 groups (from the seed) flying to 1..G-1 distinct random sites, so
  several groups share a site.

Every scenario states its minimum start spacing and slot spacing (the default controller's slot
rule: slot = site + own start offset from the centroid of the vehicles sharing that site,
``mfg_autopilot.guidance.planner.slots_from_sites``), and :func:`check_flyable` refuses one that
cannot be flown with an airframe's safety radius.

Positions are (x, y) = (north, east) in metres. ``destination_m`` is each UAV's mission
*site* (shared by its group); the default controller derives each UAV's slot from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mfg_autopilot.guidance.planner import min_spacing_m, slots_from_sites

__all__ = ["Scenario", "ScenarioError", "grid_positions", "make_scenario", "check_flyable", "SCENARIOS",
           "DEFAULT_SAFETY_RADIUS_M", "RANDOM_MIN_SPACING_M"]

DEFAULT_SAFETY_RADIUS_M = 0.05
"""Half the collision distance (metrics.COLLISION_DISTANCE_M = 0.1 m): the airframe the paper's numbers assume."""
RANDOM_MIN_SPACING_M = 1.5
"""``random``: the smallest start distance it generates."""


class ScenarioError(ValueError):
    """A scenario that cannot be generated, or cannot be flown safely."""


@dataclass(frozen=True)
class Scenario:
    name: str
    initial_pos_m: np.ndarray      # (N, 2)
    destination_m: np.ndarray      # (N, 2) each UAV's destination
    group: np.ndarray              # (N,) group index (0 for single-group scenarios)
    initial_vel_m_s: np.ndarray | None = None   # (N, 2); None: drawn from the wind (the paper's start, airborne)

    @property
    def n(self) -> int:
        return self.initial_pos_m.shape[0]

    @property
    def slots_m(self) -> np.ndarray:
        """Every vehicle's slot under the default controller's rule, (N, 2)."""
        return slots_from_sites(self.initial_pos_m, self.destination_m)

    @property
    def min_start_spacing_m(self) -> float:
        return min_spacing_m(self.initial_pos_m)

    @property
    def slot_spacing_m(self) -> float:
        return min_spacing_m(self.slots_m)


def grid_positions(n: int, spacing_m: float, centre_m) -> np.ndarray:
    """n points row by row on a square grid of ceil(sqrt(n)) columns, centred on centre_m. (n, 2)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    idx = np.arange(n)
    pts = np.stack([idx // cols, idx % cols], axis=1).astype(float) * spacing_m
    pts -= np.array([(rows - 1) * spacing_m / 2.0, (cols - 1) * spacing_m / 2.0])
    return pts + np.asarray(centre_m, dtype=float)


def _paper(n: int, spacing_m: float = np.sqrt(2.0)) -> Scenario:
    pos = grid_positions(n, spacing_m, (150.0, 100.0))
    return Scenario("paper", pos, np.zeros((n, 2)), np.zeros(n, dtype=np.int64))


def _dense(n: int) -> Scenario:
    sc = _paper(n, spacing_m=0.5)
    return Scenario("dense", sc.initial_pos_m, sc.destination_m, sc.group, initial_vel_m_s=np.zeros((n, 2)))


def _crossing(n: int, spacing_m: float = np.sqrt(2.0)) -> Scenario:
    if n < 2:
        raise ValueError(f"crossing needs n >= 2, got {n}")
    na = n // 2
    west, east = np.array([-60.0, 0.0]), np.array([60.0, 0.0])
    pos = np.concatenate([grid_positions(na, spacing_m, west), grid_positions(n - na, spacing_m, east)])
    dest = np.concatenate([np.tile(east, (na, 1)), np.tile(west, (n - na, 1))])
    group = np.concatenate([np.zeros(na, dtype=np.int64), np.ones(n - na, dtype=np.int64)])
    return Scenario("crossing", pos, dest, group)


def _split(n: int, k: int) -> list[int]:
    """n into k near-equal parts (the first n % k one larger)."""
    return [n // k + (1 if i < n % k else 0) for i in range(k)]


def _grid_half_width_m(n: int, spacing_m: float) -> float:
    return spacing_m * (int(np.ceil(np.sqrt(max(n, 1)))) - 1) / 2.0


def _swap4(n: int, rng: np.random.Generator, spacing_m: float = np.sqrt(2.0)) -> Scenario:
    if n < 4:
        raise ScenarioError(f"swap4 needs n >= 4, got {n}")
    sizes = _split(n, 4)
    r = max(60.0, 2.0 * np.sqrt(2.0) * _grid_half_width_m(sizes[0], spacing_m) + 10.0)   # groups' grids never overlap
    centres = np.array([[r, 0.0], [0.0, r], [-r, 0.0], [0.0, -r]])
    pos = np.concatenate([grid_positions(m, spacing_m, c) for m, c in zip(sizes, centres)])
    group = np.concatenate([np.full(m, g, dtype=np.int64) for g, m in enumerate(sizes)])
    dest = -centres[group]                   # the opposite side
    return Scenario("swap4", pos, dest, group)


def _circle(n: int, rng: np.random.Generator, spacing_m: float = np.sqrt(2.0)) -> Scenario:
    if n < 2:
        raise ScenarioError(f"circle needs n >= 2, got {n}")
    radius = max(20.0, spacing_m / (2.0 * np.sin(np.pi / n)))       # neighbours exactly spacing_m apart (chord)
    ang = 2.0 * np.pi * np.arange(n) / n
    pos = radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    return Scenario("circle", pos, -pos, np.arange(n, dtype=np.int64))


def _merge(n: int, rng: np.random.Generator, spacing_m: float = np.sqrt(2.0)) -> Scenario:
    k = int(rng.integers(2, 7))
    if n < k:
        k = max(1, n)
    sizes = _split(n, k)
    half = _grid_half_width_m(sizes[0], spacing_m) * np.sqrt(2.0)
    # far enough out that neighbouring sources' grids do not overlap: chord at the smallest angle >= 2 half + 10 m
    dist = max(80.0, (2.0 * half + 10.0) / (2.0 * np.sin(np.pi / max(k, 2))))
    bearing = 2.0 * np.pi * (np.arange(k) + rng.uniform(-0.15, 0.15, size=k)) / k + rng.uniform(0, 2 * np.pi)
    centres = dist * np.stack([np.cos(bearing), np.sin(bearing)], axis=1)
    pos = np.concatenate([grid_positions(m, spacing_m, c) for m, c in zip(sizes, centres)])
    group = np.concatenate([np.full(m, g, dtype=np.int64) for g, m in enumerate(sizes)])
    # one site area: each group's slot block (its grid, translated) on the side of the common centre facing
    # its source, the blocks just far enough out to stay disjoint (adjacent bearings are >= 0.7 (2 pi / k) apart).
    # (Sharing one site point would, under the slot rule, translate the whole start layout there: with the
    # sources around the site that is where they already are, and nobody would move.)
    gap = 0.7 * 2.0 * np.pi / max(k, 2)
    r_block = (2.0 * half + spacing_m) / (2.0 * np.sin(gap / 2.0)) if k > 1 else 0.0
    sites = r_block * np.stack([np.cos(bearing), np.sin(bearing)], axis=1)
    return Scenario("merge", pos, sites[group], group)


def _poisson_disc(n: int, box_m: float, min_m: float, rng: np.random.Generator) -> np.ndarray:
    """n points in [-box/2, box/2]^2, pairwise >= min_m apart: seeded rejection sampling on a grid of
    cells of side min_m / sqrt(2) (at most one point a cell), in batches."""
    cell = min_m / np.sqrt(2.0)
    side = int(np.ceil(box_m / cell))
    occupied = -np.ones((side + 4, side + 4), dtype=np.int64)
    pts = np.empty((n, 2))
    m = 0
    for _ in range(200):
        cand = rng.uniform(-box_m / 2, box_m / 2, size=(max(4 * (n - m), 64), 2))
        ij = np.floor((cand + box_m / 2) / cell).astype(np.int64) + 2
        for c, (i, j) in zip(cand, ij):
            block = occupied[i - 2:i + 3, j - 2:j + 3]
            near = block[block >= 0]
            if near.size and np.min(np.linalg.norm(pts[near] - c, axis=1)) < min_m:
                continue
            if occupied[i, j] >= 0:
                continue
            occupied[i, j] = m
            pts[m] = c
            m += 1
            if m == n:
                return pts
    raise ScenarioError(f"random: could not place {n} vehicles {min_m} m apart in a {box_m:.0f} m box")


def _random(n: int, rng: np.random.Generator, min_spacing: float = RANDOM_MIN_SPACING_M) -> Scenario:
    if n < 2:
        raise ScenarioError(f"random needs n >= 2, got {n}")
    box = max(60.0, np.sqrt(n) * min_spacing * 2.0)          # a quarter of the box's area filled at most
    pos = _poisson_disc(n, box, min_spacing, rng)
    g = int(rng.integers(2, 9)) if n >= 8 else 2
    # groups: contiguous in a random direction (a group starts together), then 1..g-1 sites shared between them
    axis = rng.normal(size=2)
    order = np.argsort(pos @ (axis / np.linalg.norm(axis)), kind="stable")
    group = np.empty(n, dtype=np.int64)
    for k, idx in enumerate(np.array_split(order, g)):
        group[idx] = k
    n_sites = int(rng.integers(1, g))
    # the groups sharing a site are neighbours (consecutive bands): g bands cut into n_sites runs at random
    cuts = np.sort(rng.choice(np.arange(1, g), size=n_sites - 1, replace=False))
    site_of_group = np.searchsorted(cuts, np.arange(g), side="right")
    # sites far apart: the slot blocks (the start layout of the vehicles sharing a site, translated) must not overlap
    reach = box * np.sqrt(2.0) / 2.0
    sites = np.empty((n_sites, 2))
    for s in range(n_sites):
        for _ in range(1000):
            c = rng.uniform(-1.5 * box, 1.5 * box, size=2)
            if s == 0 or np.min(np.linalg.norm(sites[:s] - c, axis=1)) > 2.0 * reach + min_spacing:
                sites[s] = c
                break
        else:
            sites[s] = sites[s - 1] + np.array([2.0 * reach + min_spacing, 0.0])
    return Scenario("random", pos, sites[site_of_group[group]], group)


SCENARIOS = {"paper": _paper, "crossing": _crossing, "dense": _dense, "swap4": _swap4, "circle": _circle, "merge": _merge,
             "random": _random}
SEEDED = ("swap4", "circle", "merge", "random")
"""Families whose generator takes the seed (the paper's three are fixed layouts)."""


def check_flyable(sc: Scenario, safety_radius_m: float = DEFAULT_SAFETY_RADIUS_M) -> None:
    """Refuse (ScenarioError naming the scenario, the quantity and the bound) a scenario whose starts or
    slots are closer than twice the safety radius: no controller can keep them apart there."""
    clearance = 2.0 * safety_radius_m
    for what, value in (("start spacing", sc.min_start_spacing_m), ("slot spacing", sc.slot_spacing_m)):
        if value < clearance:
            raise ScenarioError(f"scenario {sc.name!r} (N = {sc.n}) cannot be flown safely: its {what} {value:.3f} m is below "
                                f"twice the safety radius ({clearance:.3f} m)")


def scenario_from_mission(mission) -> Scenario:
    """A field mission (``mfg_autopilot.mission.Mission``) as a scenario in its swarm frame: every vehicle (in
    system-id order) from its launch position to its group's site, at the cruise altitude (the
    simulator flies the horizontal part only: no takeoff, no landing)."""
    a = mission.arrays()
    # at rest: a vehicle of a field mission starts from a hover at its altitude after its takeoff
    return Scenario(f"mission:{mission.name or 'mission'}", a["launch_ne_m"], a["site_ne_m"], a["group"],
                    initial_vel_m_s=np.zeros_like(a["launch_ne_m"]))


def mission_of_scenario(sc: Scenario, *, safety_radius_m: float = DEFAULT_SAFETY_RADIUS_M, altitude_agl_m: float = 10.0,
                        on_arrival: str = "hold", datum=None):
    """A built-in scenario as a field mission around ``datum`` (default: ``mfg_autopilot.mission.DEFAULT_DATUM``):
    one mission group per scenario group, launched on the same grid it starts on (system id = index + 1),
    flying to its site at ``altitude_agl_m``. Only grid-launched groups with a site of their own can be
    written (a mission file describes launch areas as grids and refuses overlapping slot blocks):
    ScenarioError otherwise (``random`` and ``merge`` cannot be written)."""
    from mfg_autopilot.mission import DEFAULT_DATUM, mission_from_ne

    groups = []
    for g in np.unique(sc.group):
        idx = np.flatnonzero(sc.group == g)
        pts = sc.initial_pos_m[idx]
        site = sc.destination_m[idx]
        if not np.allclose(site, site[0]):
            raise ScenarioError(f"scenario {sc.name!r}: group {g} has more than one site; a mission group has one")
        spacing = min_spacing_m(pts) if len(idx) > 1 else 2.0 * safety_radius_m
        centre = pts[0] - grid_positions(len(idx), spacing, (0.0, 0.0))[0]         # the grid's centre (not the centroid)
        if len(idx) > 1 and not np.allclose(grid_positions(len(idx), spacing, centre), pts, atol=1e-6):
            raise ScenarioError(f"scenario {sc.name!r}: group {g} does not start on a square grid; a mission file cannot "
                                f"describe its launch area")
        groups.append({"name": f"group{g}", "system_ids": [int(i) + 1 for i in idx], "launch_ne_m": centre, "site_ne_m": site[0],
                       "slot_spacing_m": spacing, "launch_spacing_m": spacing, "altitude_agl_m": altitude_agl_m})
    return mission_from_ne(groups_ne=groups, datum=DEFAULT_DATUM if datum is None else datum, safety_radius_m=safety_radius_m,
                           on_arrival=on_arrival, name=f"{sc.name}-n{sc.n}",
                           description=f"the built-in scenario {sc.name!r}, N = {sc.n}, as a field mission (mfg-swarm mission)")


def make_scenario(name: str, n: int, seed: int = 0) -> Scenario:
    """The scenario ``name`` for N = n (the seeded families draw from ``numpy.random.default_rng((seed, 7))``)."""
    try:
        factory = SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}") from None
    if name in SEEDED:
        return factory(n, np.random.default_rng((int(seed), 7)))
    return factory(n)
