"""The typed values between a controller and whoever drives it (the simulator or the vehicle process).

A controller is a *bank* of n vehicle controllers (the simulator runs one bank for all N
UAVs; ``mfg-autopilot`` runs a bank of one). Per control step t_k the caller gives an
:class:`Observation`: the own observed states, the neighbour states actually heard this step
(HJB_d only) and, for presets that have one, what the onboard proximity sensor sees. The
controller returns a :class:`StepInfo`. Nothing here does I/O, and this module imports nothing
of the project: every room may use it.

Data flow: telemetry -> Observation -> controller.step -> StepInfo.acc_m_s2 -> setpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["Neighbours", "HeardSummary", "Observation", "StepInfo", "Controller"]


@dataclass(frozen=True)
class StepInfo:
    """What one control step of a bank produced; every array has one row per vehicle."""

    acc_m_s2: np.ndarray          # (n, 2) the action a* (saturated)
    grad_evals: np.ndarray        # (n,) gradient evaluations this step (computation energy)
    reg_active: np.ndarray        # (n,) bool, R_i(t) > 0 at some inner iteration (Fig. 4)
    residual: np.ndarray          # (n,) last HJB residual H_hat
    mf_evals: np.ndarray          # (n,) mean-field evaluations this step (MFG only)


@dataclass(frozen=True)
class Neighbours:
    """A flat list of (bank row, state) pairs: ``states[m]`` was received (or sensed) by
    bank row ``owner[m]``. states: (m, 4) absolute [x_m, y_m, vx_m_s, vy_m_s]; owner: (m,)."""

    states: np.ndarray
    owner: np.ndarray
    ids: np.ndarray | None = None     # (m,) vehicle ids of the senders, where known

    @staticmethod
    def empty() -> "Neighbours":
        return Neighbours(np.zeros((0, 4)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))

    @staticmethod
    def from_pairs(states: np.ndarray, pairs: np.ndarray) -> "Neighbours":
        """Both directions of each undirected pair (i, j) of a bank holding every vehicle."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        owner = np.concatenate([pairs[:, 0], pairs[:, 1]])
        other = np.concatenate([pairs[:, 1], pairs[:, 0]])
        return Neighbours(states[other], owner, other)

    def counts(self, n: int) -> np.ndarray:
        """States per bank row, (n,)."""
        return np.bincount(self.owner, minlength=n)


@dataclass(frozen=True)
class HeardSummary:
    """Aggregates over *every* state each bank row heard this step: count (n,), sum of the
    heard positions pos_sum_m (n, 2), distance to the nearest heard vehicle nearest_m (n,)
    (inf if none). Given by a caller that delivers only the heard states within the
    controller's ``heard_cutoff_m`` reach (the simulator at large N); :meth:`of` computes it from a
    complete list (what a vehicle process holds)."""

    count: np.ndarray
    pos_sum_m: np.ndarray
    nearest_m: np.ndarray

    @staticmethod
    def of(own: np.ndarray, heard: Neighbours, n: int) -> "HeardSummary":
        cnt = heard.counts(n)
        pos_sum = np.stack([np.bincount(heard.owner, heard.states[:, d], n) for d in range(2)], axis=1)
        near = np.full(n, np.inf)
        if heard.states.shape[0]:
            dist = np.linalg.norm(heard.states[:, 0:2] - own[heard.owner, 0:2], axis=1)
            np.minimum.at(near, heard.owner, dist)
        return HeardSummary(cnt, pos_sum, near)


@dataclass(frozen=True)
class Observation:
    step: int
    time_s: float
    own_states: np.ndarray                       # (n, 4) observed, absolute
    neighbours: Neighbours | None = None         # heard this step (HJB_d)
    sensed: Neighbours | None = None             # onboard proximity sensor (no communication)
    heard_summary: HeardSummary | None = None    # aggregates of everything heard, when ``neighbours`` holds only
                                                 # the states within the controller's heard_cutoff_m reach (simulator)


class Controller(Protocol):
    mode: str
    preset: object                   # the mfg_autopilot.paper.params.Preset (or subclass) it was built with

    @property
    def n(self) -> int: ...

    @property
    def destinations_m(self) -> np.ndarray:
        """(n, 2) where each vehicle of the bank is going (valid after exchange_t0)."""
        ...

    def exchange_t0(self, states: np.ndarray, ids: np.ndarray, own_index: np.ndarray, sites_m: np.ndarray) -> None:
        """The t = 0 swarm-state exchange: all N states (N, 4), their vehicle ids (N,), for
        each bank row the index of its own vehicle in ``states`` (n,), and every vehicle's
        mission destination site (N, 2) (mission configuration, known before take-off)."""
        ...

    def step(self, obs: Observation) -> StepInfo: ...

    # Optional (the default preset's controllers; the simulator uses them when present). A *reach* is
    # (base_m, extra_m (N,)) for a bank holding every vehicle, whose observed states (N, 4) are given:
    # vehicle j can change row i's action only if |r_j - r_i| <= base + extra_i + extra_j; a third element
    # horizon_s adds: and only if min over 0 <= tau <= horizon_s of |d + tau u| <= base (d = r_j - r_i, u = v_j - v_i);
    # a fourth, wide (N,) bool, exempts the pairs of the wide rows from that test (they need every vehicle within
    # base + extra_i + extra_j: the default MFG controller's rows near a vehicle off the plan).
    # ignores_sensed_if_heard = True: sensed vehicles also heard this step do not change the action.
    # def heard_cutoff_m(self, step: int, states: np.ndarray) -> tuple[float, np.ndarray] | None:
    #     """The reach of heard states (None: every heard state matters). The caller may then put in
    #     Observation.neighbours only the heard states within it (plus those it also sensed),
    #     provided it gives Observation.heard_summary over all of them when the controller's
    #     ``needs_heard_summary`` is true; the action is the same as with the complete list (up
    #     to the summation order of the terms that remain)."""
    # def sensed_cutoff_m(self, states: np.ndarray, sensed_states: np.ndarray | None = None
    #                     ) -> tuple[float, np.ndarray] | None:
    #     """Likewise for the proximity sensor (Observation.sensed); sensed_states (N, 4): every vehicle's state
    #     as the sensor will deliver it (the same to every observer), if the caller knows it."""
    # A controller may split step(obs) into three calls (the default MFG controller does; the runtime
    # then keeps only act() between the position and the setpoint): prepare(step) (what does not
    # depend on the observation; idempotent), act(obs) -> StepInfo (the action), finish() (what only
    # later steps read, e.g. a model update). step(obs) must equal act(obs) then finish(), bit for bit.

    def weights(self) -> dict[str, np.ndarray]:
        """Learned weights for logging (e.g. {"w_H": (n, 54), "w_F": (n, 69)})."""
        ...
