"""Mission scenarios: where the UAVs start and where each one is going.

``paper`` is Sec. V: N UAVs on a square grid with sqrt(2) m spacing centred at
(150, 100) m, all flying to the origin. Positions are (x, y) = (north, east) in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Scenario", "grid_positions", "make_scenario", "SCENARIOS"]


@dataclass(frozen=True)
class Scenario:
    name: str
    initial_pos_m: np.ndarray      # (N, 2)
    destination_m: np.ndarray      # (N, 2) each UAV's destination
    group: np.ndarray              # (N,) group index (0 for single-group scenarios)

    @property
    def n(self) -> int:
        return self.initial_pos_m.shape[0]


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


SCENARIOS = {"paper": _paper}


def make_scenario(name: str, n: int) -> Scenario:
    try:
        factory = SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}") from None
    return factory(n)
