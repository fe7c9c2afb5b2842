"""A failed vehicle that PX4's Hold flies back across the stream is predicted accelerating (issue 18, thirty-second
session; BackstopParams.escape_lost_steady_*).

A gust blew failed vehicle 10 past its Hold point while it braked; PX4's Hold then flew it back at its acceleration
limit, a steady ~2 m/s^2, across the stream at up to 2.9 m/s. The escape predicted it at constant velocity (1.4 m off
at the meeting) and UAV 435 met it. The flight is the held-out run of the thirty-first round (`paper` N = 1,200 seed
162, `--gust --fail-vehicle 10 --fail-at 20.15`), flown as far as the encounter on the default airframe (PX4's lag)."""

from __future__ import annotations

import dataclasses

import pytest

from mfg_autopilot.presets import preset_by_name
from mfg_autopilot.safety.params import BackstopParams
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate

DEFAULT = preset_by_name("default")


def _fly(lead_s: float) -> dict:
    preset = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop,
                                                                       escape_lost_steady_lead_s=lead_s))
    cfg = SimConfig(scenario=make_scenario("paper", 1200, 162), mode="mfg", preset=preset, seed=162, steps=57,
                    fail_vehicle=10, fail_at_s=20.15, gust=GustParams())
    assert cfg.acc_lag_s == pytest.approx(0.154)          # the default airframe: PX4's lag
    _, m = simulate(cfg, progress=False)
    return m


def test_the_rule_is_the_default():
    assert DEFAULT.backstop.escape_lost_steady_lead_s == pytest.approx(0.5)


@pytest.mark.parametrize("name", ["escape_lost_steady_lead_s", "escape_lost_steady_min_m_s2",
                                  "escape_lost_steady_tol_m_s2"])
def test_a_negative_setting_is_refused(name):
    with pytest.raises(ValueError, match=name):
        BackstopParams(**{name: -0.1})


def test_a_failed_vehicle_flown_back_across_the_stream_is_passed():
    # Given vehicle 10 failing inside the gust, blown past its Hold point and flown back across UAV 435's lane
    led = _fly(0.5)
    constant = _fly(0.0)

    # Then predicted accelerating it is passed at more than a quarter metre; at constant velocity UAV 435 meets it
    assert led["collision_pairs"] == 0
    assert led["min_separation_m"] > 0.25
    assert constant["collision_pairs"] >= 1
    assert constant["min_separation_m"] < 0.1
