"""The plan's detour around a lost vehicle (mfg_autopilot/guidance/detour.py): the properties its docstring claims."""

from __future__ import annotations

from _traced import TRACED_CRUISE_SPACING_M
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mfg_autopilot.guidance.detour import detour_offset, detour_onset
from mfg_autopilot.guidance.params import DetourParams

P = DetourParams()
DT = 0.5


def _lanes(o, heading, across_m, along_m, speed):
    """Particles at (along, across) in the frame of a flow with ``heading`` (rad) around o, at ``speed``."""
    u = np.array([np.cos(heading), np.sin(heading)])
    n = np.array([-u[1], u[0]])
    pos = o + np.outer(along_m, u) + np.outer(across_m, n)
    vel = np.tile(speed * u, (len(along_m), 1))
    return np.hstack([pos, vel]), u, n


@settings(max_examples=200, deadline=None)
@given(heading=st.floats(-np.pi, np.pi), spacing=st.floats(0.3, 3.0), offset=st.floats(-0.5, 0.5),
       along=st.floats(-12.0, 12.0), clear=st.floats(0.05, 0.85), speed=st.floats(0.6, 6.0))
def test_lanes_keep_their_order_compress_at_most_by_one_minus_c_over_w_and_clear_the_vehicle(heading, spacing, offset,
                                                                                             along, clear, speed):
    o = np.array([3.0, -2.0])
    across = (np.arange(-8, 9) + offset) * spacing
    part, u, n = _lanes(o, heading, across, np.full(across.size, along), speed)
    ds, _ = detour_offset(part, np.zeros((across.size, 2)), np.tile(o, (across.size, 1)), np.ones(across.size), clear,
                          P, DT)
    # only across the track
    assert np.allclose(ds[:, 0:2] @ u, 0.0, atol=1e-9)
    y_new = across + ds[:, 0:2] @ n
    gaps = np.diff(y_new)
    assert np.all(gaps >= (1.0 - clear / P.width_m) * spacing - 1e-9)
    if abs(along) <= P.plateau_m:
        # on the plateau every lane passes the vehicle at least c across
        assert np.all(np.abs(y_new) >= clear - 1e-9)
    far = (np.abs(across) >= P.width_m) | (abs(along) >= P.plateau_m + P.ramp_m)
    assert np.allclose(ds[far], 0.0)


def test_the_support_lies_inside_the_sensor_range():
    from mfg_autopilot.safety.params import BackstopParams
    reach = np.hypot(P.plateau_m + P.ramp_m, P.width_m)
    assert reach < BackstopParams().sensor_range_m - 0.5


def test_the_deflection_flown_through_the_plant_matches_its_velocity_and_mean_acceleration():
    """A particle flying straight at 4 m/s through the vehicle: the deflection's velocity is the derivative of its
    position, and its mean acceleration over a step the velocity change; its peak is c (pi / ramp)^2 / 2 v^2."""
    o = np.zeros(2)
    speed, c = 4.0, 0.85
    t = np.arange(0.0, 6.0, DT)
    along = -12.0 + speed * t
    part, u, n = _lanes(o, 0.3, np.zeros(t.size), along, speed)
    ds, da = detour_offset(part, np.zeros((t.size, 2)), np.zeros((t.size, 2)), np.ones(t.size), c, P, DT,
                           np.full(t.size, -1.0))
    y = ds[:, 0:2] @ n
    vy = ds[:, 2:4] @ n
    ay = da @ n
    assert y.min() <= -c + 1e-9           # on the side given
    assert np.allclose(ay[:-1], np.diff(vy) / DT)
    # the trapezoidal rule on the velocity gives the position to third order in dt (a 2 m step on the 8 m ramp: < 3 cm)
    assert np.max(np.abs(np.diff(y) - 0.5 * (vy[1:] + vy[:-1]) * DT)) < 0.03
    assert np.max(np.abs(ay)) <= c * (np.pi / P.ramp_m) ** 2 / 2 * speed ** 2 + 1e-9


def test_onset_and_slow_particles():
    a = detour_onset(P.onset_from_m + np.array([-1.0, 0.0, 0.5 * P.onset_m, P.onset_m, 40.0]), P)
    assert np.allclose(a, [0.0, 0.0, 0.5, 1.0, 1.0])
    o = np.zeros(2)
    part, _, _ = _lanes(o, 0.0, np.array([0.1, 0.1, 0.1]), np.zeros(3), 1.0)
    part[:, 2:4] *= np.array([[1.0], [0.5 * P.min_speed_m_s], [0.0]])
    ds, _ = detour_offset(part, np.zeros((3, 2)), np.zeros((3, 2)), np.ones(3), 0.8, P, DT)
    mag = np.linalg.norm(ds[:, 0:2], axis=1)
    assert mag[0] > 0.6 and np.isclose(mag[1], 0.5 * mag[0]) and mag[2] == 0.0


def test_the_side_is_the_lanes_and_right_through_the_vehicle():
    from mfg_autopilot.guidance.detour import detour_side
    o = np.array([1.0, 1.0])
    part, _, _ = _lanes(o, 0.7, np.array([0.3, -0.3]), np.array([-5.0, 2.0]), 4.0)
    assert np.array_equal(detour_side(part, np.tile(o, (2, 1))), [1.0, -1.0])
    part[:, 0:2] = o + np.array([[-3.0, 0.0], [3.0, 0.0]])
    part[:, 2:4] = [4.0, 0.0]
    assert np.array_equal(detour_side(part, np.tile(o, (2, 1))), [-1.0, -1.0])


def test_a_turning_lane_passes_on_the_side_where_it_meets_the_vehicle():
    """A rigid turn's lane is an arc: 8 m before the vehicle it lies 0.3 m left of it but passes it 0.34 m right."""
    from mfg_autopilot.guidance.detour import detour_side
    R, speed = 50.0, 4.0
    o = np.array([0.0, 0.0])
    # the particle on a circle of radius R, turning right (clockwise), at its top 0.34 m right of the vehicle
    c = np.array([0.0, -R - 0.34])
    th = np.arctan2(8.0, R)                     # 8 m of arc before the top (where it passes o)
    p = c + R * np.array([-np.sin(th), np.cos(th)])
    v = speed * np.array([np.cos(th), np.sin(th)])
    a = speed ** 2 / R * (c - p) / R             # centripetal
    part = np.hstack([p, v])[None, :]
    d = p - o
    y_now = (v[0] * d[1] - v[1] * d[0]) / speed
    assert 0.2 < y_now < 0.4                     # seen along the track now, the lane lies left of the vehicle
    assert detour_side(part, o[None, :])[0] == 1.0
    assert detour_side(part, o[None, :], a[None, :])[0] == -1.0     # it passes it on its right


def _passes_after_onset(preset, scenario="paper", n=100, seed=0, fail_vehicle=10, fail_at_s=20.0, steps=160):
    """(metrics, the smallest distance of any UAV to the failed vehicle along the step segments from 4 s after its
    failure on: when the lanes near it are deflected in full)."""
    from mfg_swarm.metrics import segment_min_distance
    from mfg_swarm.scenarios import make_scenario
    from mfg_swarm.sim import SimConfig, simulate
    # (the paper's plant, as this was measured: with PX4's lag the lanes pass 0.56 m off, the test's bound 0.5 m; issue 18)
    tr, m = simulate(SimConfig(scenario=make_scenario(scenario, n), mode="mfg", preset=preset, seed=seed, steps=steps,
                               fail_vehicle=fail_vehicle, fail_at_s=fail_at_s, acc_lag_s=0.0), progress=False)
    d = tr.pos_m - tr.pos_m[:, fail_vehicle:fail_vehicle + 1]
    d = np.delete(d, fail_vehicle, axis=1)
    k0 = int(round((fail_at_s + 4.0) / tr.dt_s))
    return m, float(np.min(segment_min_distance(d[k0:-1].reshape(-1, 2), d[k0 + 1:].reshape(-1, 2))))


def test_the_lanes_pass_a_failed_vehicle_deflected_together():
    """paper N = 100, vehicle 10 fails into Hold at 20 s and the block flies past it: with the detour every UAV passes
    it at >= 0.6 m (c = 0.85 m, less the tracking error) once the lanes are deflected, against 0.48 m by the escape
    alone (the escape is the backstop of each UAV by itself: it cannot move the neighbouring lanes)."""
    import dataclasses

    from mfg_autopilot.presets import preset_by_name
    # the plan this was measured on, paper's block unspread (tests/_traced.py; at 2.1 m the block passes the failed
    # vehicle with room and the escape alone keeps more than 0.5 m)
    on = dataclasses.replace(preset_by_name("default"), cruise_spacing_m=TRACED_CRUISE_SPACING_M)
    off = dataclasses.replace(on, detour=dataclasses.replace(on.detour, enabled=False))
    m_on, pass_on = _passes_after_onset(on)
    m_off, pass_off = _passes_after_onset(off)
    assert m_on["collision_pairs"] == 0 and m_on["arrived_fraction_others"] == 1.0
    assert pass_on >= 0.6, pass_on
    assert pass_off < 0.5, pass_off
    # fewer interventions of the backstop: the plan, not the escape, keeps the lanes clear of it
    assert m_on["safety_interventions"] < m_off["safety_interventions"]
    # the guarantee check reads the references as deflected: the lanes were compressed (the plan's 1.41 m spacing is
    # no longer the smallest distance of the tracked references), by at most 1 - c / W
    g_on, g_off = m_on["guarantee"], m_off["guarantee"]
    assert g_off["plan_min_separation_m"] >= np.sqrt(2.0) - 1e-3
    c = min(on.detour.clear_max_m, on.detour.clear_fraction * np.sqrt(2.0))
    assert (1.0 - c / on.detour.width_m) * np.sqrt(2.0) - 1e-3 <= g_on["plan_min_separation_m"] < np.sqrt(2.0) - 0.1


def _hold_flight(controllers, sc, plant_seed, K, fail_at_s, steps, reused=None):
    """Fly sc with the bank(s) in ``controllers`` deciding (the first one's commands flown; every one's returned per
    step), vehicle K failing into PX4's jerk-limited Hold at fail_at_s (the simulator's ``_step_with_hold``).
    Returns (per step the list of the controllers' commands, the rows the first bank deflected)."""
    from scipy.spatial import cKDTree

    from mfg_autopilot.interface import Neighbours, Observation
    from mfg_swarm.sim import _step_with_hold, as_f32, plant_params_for
    from mock_vehicle.plant import SwarmPlant, braking_stop_m

    preset = controllers[0][0].preset
    plant = SwarmPlant(sc.initial_pos_m, plant_params_for(preset), seed=plant_seed)
    S0 = as_f32(plant.states)
    n, ids = sc.n, np.arange(sc.n)
    for bank, own_index, sites in controllers:
        bank.exchange_t0(S0, ids, own_index, sites)
    hold, hold_acc, last = None, np.zeros(2), np.zeros((n, 2))
    out, deflected = [], set()
    for k in range(steps):
        obs = as_f32(plant.states)
        sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(controllers[0][0].sensor_range_m,
                                                                            output_type="ndarray"))
        acts = []
        for bank, own_index, _ in controllers:
            if own_index.size == n:
                acts.append(bank.step(Observation(k, k * preset.dt_s, obs, None, sensed)).acc_m_s2)
            else:
                i = int(own_index[0])
                m = sensed.owner == i
                own = Neighbours(sensed.states[m], np.zeros(int(m.sum()), dtype=np.int64), sensed.ids[m])
                acts.append(bank.step(Observation(k, k * preset.dt_s, obs[i:i + 1], None, own)).acc_m_s2)
        first = controllers[0][0]
        if first._detour_state is not None:
            deflected |= set(np.flatnonzero(first._detour_state[0] & (first._detour_state[2] > 0)).tolist())
        out.append(acts)
        a = as_f32(acts[0])
        if k * preset.dt_s >= fail_at_s:
            if hold is None:
                hold, hold_acc = braking_stop_m(obs[K:K + 1]), last[K].copy()
            last, hold_acc, _ = _step_with_hold(plant, a, preset.dt_s, K, hold, hold_acc, 4.0)
        else:
            last = plant.step(a, preset.dt_s)
    return out, deflected


def test_a_bank_of_one_per_vehicle_deflects_exactly_as_the_bank_of_all():
    """The detour is decided by each UAV from its own observation (the sensed states and ids, the plan from the t = 0
    exchange): N controllers of one vehicle each (the process swarm) command bit for bit what one bank of N commands,
    while the lanes pass a vehicle that failed into PX4's Hold (paper N = 25, vehicle 2 in the front row fails at 5 s
    and the four rows behind fly past it)."""
    from mfg_autopilot.presets import make_controller, preset_by_name
    from mfg_swarm.scenarios import make_scenario

    preset = preset_by_name("default")
    sc = make_scenario("paper", 25)
    n, K = sc.n, 2
    bank = (make_controller("mfg", preset, sc.destination_m), np.arange(n), sc.destination_m)
    singles = [(make_controller("mfg", preset, sc.destination_m[i:i + 1]), np.array([i]), sc.destination_m)
               for i in range(n)]
    out, deflected = _hold_flight([bank] + singles, sc, 3, K, 5.0, 70)
    for acts in out:
        np.testing.assert_array_equal(acts[0], np.concatenate(acts[1:]))
    # the flight exercised the detour: several rows flew the deflected plan
    assert len(deflected - {K}) >= 4, deflected


def test_a_controller_reused_for_another_flight_decides_as_a_new_one():
    """The t = 0 exchange starts a flight: a bank that flew past a failed vehicle (its detour's memory of the side, its
    learnt value model, its tracked reference all set) and then gets another t = 0 exchange commands bit for bit what
    a new bank commands on the second flight (paper N = 25, vehicle 2 failing into Hold in both flights)."""
    from mfg_autopilot.presets import make_controller, preset_by_name
    from mfg_swarm.scenarios import make_scenario

    preset = preset_by_name("default")
    sc = make_scenario("paper", 25)
    used = make_controller("mfg", preset, sc.destination_m)
    rows = np.arange(sc.n)
    _, deflected = _hold_flight([(used, rows, sc.destination_m)], sc, 3, 2, 5.0, 60)
    assert len(deflected - {2}) >= 4 and used._detour_mem is not None and np.any(used._detour_mem[0] >= 0)
    new = make_controller("mfg", preset, sc.destination_m)
    out, deflected = _hold_flight([(used, rows, sc.destination_m), (new, rows, sc.destination_m)], sc, 4, 2, 3.0, 60)
    assert len(deflected - {2}) >= 4, deflected
    for k, (a_used, a_new) in enumerate(out):
        np.testing.assert_array_equal(a_used, a_new, err_msg=f"step {k}")
