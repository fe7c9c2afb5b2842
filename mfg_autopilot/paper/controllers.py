"""The paper's controllers: HJB_d (Algorithm 3) and MFG (Algorithm 4) as controller banks.

Each is a bank of n vehicle controllers with the interface of :mod:`mfg_autopilot.interface`
(Observation in, StepInfo out); the algorithms themselves are in :mod:`~mfg_autopilot.paper.learners`.
The `paper` preset is faithful and, as SPEC section 3 predicts, neither arrives nor avoids
collisions (docs/errata.md); the product controller is :mod:`mfg_autopilot.guidance`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mfg_autopilot.interface import Neighbours, Observation, StepInfo
from mfg_autopilot.paper.costs import cs_kernel
from mfg_autopilot.paper.learners import HJBLearner, MFGLearner
from mfg_autopilot.paper.params import Preset

__all__ = ["PaperHJBController", "PaperMFGController"]


def _phi_G_from(own: np.ndarray, nb: Neighbours | None, preset: Preset) -> np.ndarray:
    """phi_G of eq. 3 per bank row: mean Cucker-Smale kernel over the states heard."""
    n = own.shape[0]
    if nb is None or nb.states.shape[0] == 0:
        return np.zeros(n)
    k = cs_kernel(own[nb.owner], nb.states, preset.cost)
    cnt = np.bincount(nb.owner, minlength=n)
    return np.where(cnt > 0, np.bincount(nb.owner, k, n) / np.maximum(cnt, 1), 0.0)


@dataclass
class _Base:
    preset: Preset
    destination_site_m: np.ndarray               # (n, 2) mission destination of each bank row
    _dest4: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.destination_site_m = np.asarray(self.destination_site_m, dtype=float).reshape(-1, 2)
        self._dest4 = np.concatenate([self.destination_site_m, np.zeros_like(self.destination_site_m)], axis=1)

    @property
    def n(self) -> int:
        return self.destination_site_m.shape[0]

    @property
    def destinations_m(self) -> np.ndarray:
        return self.destination_site_m


class PaperHJBController(_Base):
    """HJB_d with the paper's Algorithm 3 (the `paper` preset)."""

    mode = "hjb"

    def __post_init__(self) -> None:
        super().__post_init__()
        self.learner = HJBLearner(self.n, self.preset)

    def exchange_t0(self, states, ids, own_index, sites_m) -> None:
        """HJB_d has no swarm-wide exchange: states arrive with each step's gossip."""

    def step(self, obs: Observation) -> StepInfo:
        phi_g = _phi_G_from(obs.own_states, obs.neighbours, self.preset)
        return self.learner.step(obs.own_states - self._dest4, phi_g)

    def weights(self) -> dict[str, np.ndarray]:
        return {"w_H": self.learner.w_H.copy()}


class PaperMFGController(_Base):
    """MFG learning control with the paper's Algorithm 4 (the `paper` preset)."""

    mode = "mfg"

    def __post_init__(self) -> None:
        super().__post_init__()
        self.learner = MFGLearner(self.n, self.preset)

    def exchange_t0(self, states, ids, own_index, sites_m) -> None:
        self.learner.initialise(np.asarray(states, dtype=float), np.asarray(sites_m, dtype=float), np.asarray(own_index))

    def step(self, obs: Observation) -> StepInfo:
        return self.learner.step(obs.own_states - self._dest4)

    def weights(self) -> dict[str, np.ndarray]:
        out = {"w_H": self.learner.w_H.copy()}
        if self.learner.mean_field is not None:
            out["w_F"] = self.learner.mean_field.w_F.copy()
        return out


