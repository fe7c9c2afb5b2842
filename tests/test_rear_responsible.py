"""The UAV behind is the responsible one (BackstopParams.escape_rear_responsible): a row does not wake its escape for a
healthy vehicle behind it, and a closing pair always keeps one UAV that escapes.

After a gust two healthy UAVs escaping each other at once each predicted the other flying straight on and swerved into
each other (circle --gust with a failure, N = 2,000 s231: UAVs 248 / 252, 0.064 m; 0.139 m with the rule).
docs/default_controller.md, "The UAV behind is the responsible one".
"""
from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mfg_autopilot.guidance.controller import DefaultHJBController
from mfg_autopilot.guidance.params import DEFAULT
from mfg_autopilot.safety.backstop import behind_row
from test_hover_latch import _controller


def test_behind_is_along_the_rows_own_velocity():
    # given a row flying east at 3 m/s and four vehicles around it
    own = np.array([[0.0, 0.0, 3.0, 0.0]])
    sensed = np.array([[2.0, 0.5, 3.0, 0.0],      # ahead
                       [-2.0, 0.5, 5.0, 0.0],     # behind, coming faster
                       [0.0, 1.0, -3.0, 0.0],     # abeam: not behind
                       [-0.1, -3.0, 0.0, 3.0]])   # just behind, crossing
    assert behind_row(own, sensed, np.zeros(4, dtype=np.int64)).tolist() == [False, True, False, True]
    # ... unless it comes within its clearance inside the reaction time (imminent: the row acts whoever is responsible).
    # With a 0.5 m clearance: the one 2.06 m behind closes at 1.94 m/s (1.56 m to go), the crossing one 3.0 m off at
    # 2.90 m/s (2.50 m to go): both within 1 s, neither within 0.5 s
    owner = np.zeros(4, dtype=np.int64)
    clear = np.full(4, 0.5)
    assert behind_row(own, sensed, owner, clear, 1.0).tolist() == [False, False, False, False]
    assert behind_row(own, sensed, owner, clear, 0.5).tolist() == [False, True, False, True]
    assert behind_row(own, sensed, owner, np.full(4, 1.2), 0.5).tolist() == [False, False, False, True]   # 0.86 / 1.80 m to go
    # a row at rest has nothing behind it; no entries, no answer
    assert not behind_row(np.zeros((1, 4)), sensed, np.zeros(4, dtype=np.int64)).any()
    assert behind_row(own, np.zeros((0, 4)), np.zeros(0, dtype=np.int64)).shape == (0,)


_coord = st.floats(-20.0, 20.0, allow_nan=False)
_speed = st.floats(-6.0, 6.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(_coord, _coord, _speed, _speed, _coord, _coord, _speed, _speed)
def test_a_closing_pair_always_keeps_one_responsible_uav(x1, y1, u1, w1, x2, y2, u2, w2):
    # for any two vehicles i, j that close on each other, at least one of them does not have the other behind it
    s = np.array([[x1, y1, u1, w1], [x2, y2, u2, w2]])
    dp, dv = s[1, 0:2] - s[0, 0:2], s[1, 2:4] - s[0, 2:4]
    if float(dp @ dv) < 0.0:
        i_sees_j = behind_row(s[0:1], s[1:2], np.zeros(1, dtype=np.int64))[0]
        j_sees_i = behind_row(s[1:2], s[0:1], np.zeros(1, dtype=np.int64))[0]
        assert not (i_sees_j and j_sees_i)


def test_the_rule_is_the_mfg_default_and_hjb_d_does_not_apply_it():
    assert DEFAULT.backstop.escape_rear_responsible
    assert _controller()._rear_responsible()
    off = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, escape_rear_responsible=False))
    assert not _controller(off)._rear_responsible()
    assert not DefaultHJBController._rear_responsible(None)
