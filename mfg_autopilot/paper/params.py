"""Parameters of the paper's model and learners, declared once with units.

Symbols and values are those of Sec. II and Sec. V of the paper; the values it does
not give (beta, K) and the fixes that finite numbers need (state scaling, action
saturation) are documented in ``docs/errata.md`` with their reasons.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["CostParams", "RadioParams", "LearnerParams", "Preset", "PAPER", "PAPER_LQR", "radio_range_m"]


@dataclass(frozen=True)
class CostParams:
    """Cost of eq. 3 and the controller's model of eq. 9 (paper Sec. V values)."""

    c0_per_s: float = 0.1          # c0, wind relaxation rate, 1/s
    c1: float = 100.0              # weight of |r|^2 (travel time)
    c2: float = 1.5                # weight of |v|^2 (kinetic energy)
    c3: float = 1.5                # weight of |a|^2 (control energy)
    c4: float = 0.5                # weight of phi_G (Cucker-Smale interaction)
    eps_m2: float = 1e-3           # epsilon of phi_G, m^2
    beta: float = 1.0              # beta of phi_G (not given by the paper; docs/errata.md)
    mean_wind_m_s: tuple[float, float] = (1.0, -1.0)                                # v_o
    wind_diffusion_m_s: tuple[tuple[float, float], tuple[float, float]] = ((0.1, 0.0), (0.0, 0.1))  # V_o

    @property
    def v_o(self) -> np.ndarray:
        return np.asarray(self.mean_wind_m_s, dtype=float)

    @property
    def V_o(self) -> np.ndarray:
        return np.asarray(self.wind_diffusion_m_s, dtype=float)


@dataclass(frozen=True)
class RadioParams:
    """Path-loss radio model of Sec. II: d = [P / (theta sigma^2)]^(1/alpha)."""

    alpha: float = 2.0             # path-loss exponent
    noise_mw: float = 2e-2         # sigma^2, mW
    snr_min_db: float = -10.0      # theta, dB


def radio_range_m(power_mw: float, radio: RadioParams = RadioParams()) -> float:
    """Communication range d(P) of Sec. II. With the paper's sigma^2 = 2e-2 mW this is
    0.707 m for P = 1e-3 mW and 70.7 m for P = 10 mW (SPEC erratum 2)."""
    if not (np.isfinite(power_mw) and power_mw > 0):
        raise ValueError(f"power_mw must be finite and > 0, got {power_mw}")
    theta = 10.0 ** (radio.snr_min_db / 10.0)
    return float((power_mw / (theta * radio.noise_mw)) ** (1.0 / radio.alpha))


@dataclass(frozen=True)
class LearnerParams:
    """Online learning of Algorithms 3 and 4."""

    mu: float = 0.01               # normalised gradient step of the HJB / FPK losses
    c_H: float = 0.5               # weight of the regulariser R
    K: int = 5                     # HJB/FPK iterations per control step (Algorithm 4; not given)
    w_H_init: str = "zero"         # "zero" (paper: w(0) = 0) or "lqr" (Riccati value of the LQ part)
    acc_max_m_s2: float = 2.0      # saturation of the action a* (erratum: finite numbers)
    state_scale: tuple[float, float, float, float] = (200.0, 200.0, 2.0, 2.0)
    """Scale of sigma_H's input: s_tilde = s / state_scale (m, m, m/s, m/s)."""
    fpk_scale: tuple[float, float, float, float] = (10.0, 10.0, 2.0, 2.0)
    """Scale of sigma_F's input, in the mean field's co-moving frame."""
    fpk_kde_bandwidth: tuple[float, float, float, float] = (1.0, 1.0, 0.3, 0.3)
    """Kernel widths of the t = 0 density that w_F(0) is fitted to (SPEC erratum 7)."""

    def __post_init__(self) -> None:
        if self.K < 1:
            raise ValueError(f"K must be >= 1, got {self.K}")
        if self.w_H_init not in ("zero", "lqr"):
            raise ValueError(f"w_H_init must be 'zero' or 'lqr', got {self.w_H_init!r}")
        if not self.acc_max_m_s2 > 0:
            raise ValueError("acc_max_m_s2 must be > 0")


@dataclass(frozen=True)
class Preset:
    """A named controller configuration."""

    name: str
    cost: CostParams = field(default_factory=CostParams)
    learner: LearnerParams = field(default_factory=LearnerParams)
    dt_s: float = 1.0              # control period Delta t

    def with_(self, **kw) -> "Preset":
        return replace(self, **kw)


PAPER = Preset(name="paper")
"""The paper's algorithms and parameters with only the errata fixes that finite numbers
require: state scaling, the action's sign, and saturation of |a|."""


PAPER_LQR = Preset(name="paper-lqr", learner=LearnerParams(w_H_init="lqr"))
"""The paper's algorithms with w_H(0) set to the Riccati value of the cost's LQ part
instead of 0 (SPEC section 3: with it every UAV arrives, but they collide at the
destination). Registered so that the effect of the warm start can be measured alone."""

