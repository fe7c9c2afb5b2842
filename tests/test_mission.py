"""Mission files: validated at load; a malformed or unsafe mission is refused naming the field (issue 19)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mfg_autopilot.mission import MissionError, load_mission, mission_from_ne
from mfg_autopilot.mission.mission import DEFAULT_DATUM

FIELD = Path(__file__).resolve().parents[1] / "examples" / "field.json"


def _field() -> dict:
    return json.loads(FIELD.read_text())


def test_given_the_example_field_when_loaded_then_it_has_16_plus_vehicles_with_launches_spread_over_a_km():
    m = load_mission(FIELD)
    a = m.arrays()
    assert m.n >= 16 and len(m.groups) >= 2 and m.on_arrival == "land"
    assert a["system_id"].tolist() == list(range(1, m.n + 1))
    launch = a["launch_ne_m"]
    spread = max(np.linalg.norm(launch[i] - launch[j]) for i in range(m.n) for j in range(m.n))
    assert spread >= 1000.0
    # slots and launch positions: twice the safety radius apart, inside the fence
    for pts in (a["slot_ne_m"], a["launch_ne_m"]):
        d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(m.n) * 1e9
        assert d.min() >= 2 * m.safety_radius_m
    assert len(set(a["altitude_agl_m"].tolist())) == len(m.groups)        # one altitude layer per group


def test_a_mission_loads_from_a_path_a_json_text_and_a_dict_alike():
    d = _field()
    assert load_mission(FIELD) == load_mission(json.dumps(d)) == load_mission(d)


@pytest.mark.parametrize("edit,field,reason", [
    (lambda d: d.pop("datum"), "", "'datum' is a required property"),
    (lambda d: d.update(safty_radius_m=1.0), "", "Additional properties"),
    (lambda d: d["datum"].update(lat_deg=123.0), "datum.lat_deg", "greater than the maximum"),
    (lambda d: d["groups"][1]["site"].update(lon_deg="8.5"), "groups[1].site.lon_deg", "not of type 'number'"),
    (lambda d: d.update(on_arrival="crash"), "on_arrival", "is not one of"),
    (lambda d: d["groups"][0]["system_ids"].append(400), "groups[0].system_ids[5]", "maximum"),
    (lambda d: d["groups"][1]["system_ids"].__setitem__(0, 1), "groups[1].system_ids[0]", r"system id 1 is already in groups\[0\]"),
    (lambda d: d["groups"][2].update(slot_spacing_m=0.6), "groups[2].slot_spacing_m", "closer than twice the safety radius"),
    (lambda d: d["groups"][2]["launch"].update(spacing_m=0.9), "groups[2].launch.spacing_m", "closer than twice the safety radius"),
    (lambda d: d["groups"][3]["site"].update(lat_deg=47.5), "groups[3].site", "outside the geofence"),
    (lambda d: d["groups"][0]["launch"].update(lon_deg=8.6), "groups[0].launch", "outside the geofence"),
    (lambda d: d["groups"][1].update(altitude_agl_m=80), "groups[1].altitude_agl_m", "above the geofence ceiling"),
    (lambda d: d["groups"][1]["site"].update(d["groups"][0]["site"]), "groups[1].site", "come within"),
    (lambda d: d["geofence"].update(polygon=[[47.39, 8.53], [47.41, 8.56], [47.39, 8.56], [47.41, 8.53]]), "geofence.polygon",
     "not a simple polygon"),
    (lambda d: d["datum"].update(lat_deg=48.5), "datum", "km from the geofence"),
])
def test_given_a_malformed_or_unsafe_mission_when_loaded_then_it_is_refused_naming_the_field(edit, field, reason):
    d = copy.deepcopy(_field())
    edit(d)
    with pytest.raises(MissionError, match=reason) as exc:
        load_mission(d)
    assert exc.value.field == field, str(exc.value)
    assert str(exc.value).startswith(field or "(mission)")


def test_an_unknown_system_id_is_refused():
    m = load_mission(FIELD)
    with pytest.raises(MissionError, match="unknown system id 99"):
        m.group_of(99)


def test_a_missing_file_and_bad_json_are_clear_errors(tmp_path):
    with pytest.raises(MissionError, match="cannot read mission file"):
        load_mission(tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text("{ not json")
    with pytest.raises(MissionError, match="not JSON"):
        load_mission(tmp_path / "bad.json")


@settings(max_examples=30, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(groups=st.lists(st.tuples(st.integers(1, 9), st.floats(-800, 800), st.floats(-800, 800), st.floats(1.0, 5.0),
                                 st.floats(5.0, 100.0)), min_size=1, max_size=4),
       radius=st.floats(0.05, 0.45))
def test_property_a_valid_generated_mission_round_trips_through_its_file_form(groups, radius):
    sid, spec = 1, []
    for k, (n, north, east, spacing, alt) in enumerate(groups):
        spec.append({"name": f"g{k}", "system_ids": list(range(sid, sid + n)), "launch_ne_m": (north, east),
                     "site_ne_m": (north / 4 + 200.0 * k, east / 4), "slot_spacing_m": spacing, "altitude_agl_m": alt})
        sid += n
    try:
        m = mission_from_ne(groups_ne=spec, safety_radius_m=radius)
    except MissionError as exc:               # overlapping launch grids of random groups: refused, for the right reason
        assert "come within" in str(exc)
        return
    again = load_mission(json.loads(json.dumps(m.to_dict())))
    assert again == m
    for g, s in zip(m.groups, spec):
        assert np.allclose(g.site_ne_m, s["site_ne_m"], atol=1e-6) and np.allclose(g.launch_ne_m, s["launch_ne_m"], atol=1e-6)


def test_the_default_datum_is_px4_sitls_home():
    assert (DEFAULT_DATUM.lat_deg, DEFAULT_DATUM.lon_deg) == (47.397742, 8.545594)
