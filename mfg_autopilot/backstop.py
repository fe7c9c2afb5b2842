"""Communication-free safety backstop: an onboard proximity sensor of short range.

Per sensed vehicle j (relative position d = r_j - r_i, relative velocity u = v_j - v_i,
both from the sensor; no communication), the predicted closest approach over the
horizon is rho = |d + tau* u|, tau* = clip(-d.u / |u|^2, 0, horizon) (tau* = 0, i.e. the
current distance, when |u| < u_noise: the wind's velocity jitter at hover, ~0.2 m/s, is
not extrapolated - it would fire in the dense formation). Only if
rho < trigger does the backstop act, with the acceleration that (to second order) would
open the closest approach to the target clearance (> trigger) by tau*:

    delta_a = -n_hat * share * 2 (target - rho) / max(tau*, tau_min)^2,   n_hat = (d + tau* u) / rho

(share = 1/2: reciprocal, each vehicle takes half; a vehicle that does not react - a failed
one - leaves the other with half per step, and the next step's prediction asks again).

(n_hat = u rotated +90 deg for an exact head-on approach: both pass 'on the right').
Contributions are summed and capped at a_max; the result is a half-plane constraint on the
command (:func:`apply_backstop`: the nearest command to the nominal one whose component
along delta_a is at least |delta_a|). With nothing predicted below the trigger the command
is returned unchanged (inactive otherwise).

Shapes: own (n, 4); sensed states (m, 4) owned by bank rows owner (m,).
"""

from __future__ import annotations

import numpy as np

from .default_params import BackstopParams
from .planner import cap_norm

__all__ = ["backstop_acc", "apply_backstop"]


def backstop_acc(own: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, bp: BackstopParams) -> np.ndarray:
    """The backstop's correction delta_a per bank row, (n, 2) (zero rows where inactive)."""
    n = own.shape[0]
    out = np.zeros((n, 2))
    if sensed_states.shape[0] == 0:
        return out
    d = sensed_states[:, 0:2] - own[owner, 0:2]
    u = sensed_states[:, 2:4] - own[owner, 2:4]
    uu = np.einsum("pd,pd->p", u, u)
    tau = np.clip(-np.einsum("pd,pd->p", d, u) / np.maximum(uu, 1e-12), 0.0, bp.horizon_s)
    tau = np.where(uu >= bp.u_noise_m_s ** 2, tau, 0.0)          # wind jitter is not a trend
    c = d + tau[:, None] * u
    rho = np.linalg.norm(c, axis=1)
    act = rho < bp.trigger_m
    if not np.any(act):
        return out
    un = np.sqrt(uu)
    perp = np.stack([-u[:, 1], u[:, 0]], axis=1) / np.maximum(un, 1e-12)[:, None]
    n_hat = np.where((rho > 1e-6)[:, None], c / np.maximum(rho, 1e-12)[:, None], np.where((un > 1e-9)[:, None], perp, np.array([[1.0, 0.0]])))
    mag = np.where(act, bp.share * 2.0 * (bp.target_m - rho) / np.maximum(tau, bp.tau_min_s) ** 2, 0.0)
    f = -mag[:, None] * n_hat
    for dim in range(2):
        out[:, dim] = np.bincount(owner, f[:, dim], n)
    return cap_norm(out, bp.a_max_m_s2)


def apply_backstop(a_nom: np.ndarray, delta_a: np.ndarray, a_max_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimal intervention as a half-plane constraint (a one-constraint safety filter):
    with n = delta_a / |delta_a| and a_req = |delta_a|, the command is the point nearest to
    a_nom with n.a >= a_req - the nominal keeps everything that does not push against the
    backstop, and is unchanged if it already satisfies it. Under the limit a_max the normal
    component is kept and the tangential one shortened. Returns (command (n, 2), active (n,))."""
    a_req = np.linalg.norm(delta_a, axis=1)
    active = a_req > 0
    n_hat = delta_a / np.maximum(a_req, 1e-300)[:, None]
    a_n_nom = np.einsum("nd,nd->n", a_nom, n_hat)
    a_n = np.minimum(np.maximum(a_req, a_n_nom), a_max_m_s2)
    tang = a_nom - a_n_nom[:, None] * n_hat
    tang = cap_norm(tang, np.sqrt(np.maximum(a_max_m_s2 ** 2 - a_n ** 2, 0.0)))
    a = np.where(active[:, None], a_n[:, None] * n_hat + tang, a_nom)
    return cap_norm(a, a_max_m_s2), active
