"""The plan the traced rule tests were written on.

Each of these tests flies the encounter its backstop rule was traced from and compares the flight with and without the
rule. They were traced when the default cruise spacing was 1.4 m (until the thirty-third session). On the current 2.1 m
default the UAVs behind a failed vehicle have room to pass it without the rule, so the counterfactual no longer
collides and a with/without comparison would show nothing (docs/default_controller.md, "Room behind every UAV"). So
they fly the plan they were traced on; the rules themselves are the default's. A rule that matters at 2.1 m should get
its own trace there.
"""

TRACED_CRUISE_SPACING_M = 1.4
