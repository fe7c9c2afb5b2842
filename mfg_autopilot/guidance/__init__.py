"""The product controller (the ``default`` preset): where each vehicle should go and how fast.

After the t = 0 exchange every vehicle computes the same interacting mean-field plan
(:mod:`.planner`: slots at the destination site, the goal term, closest-approach repulsion) and
tracks its own particle with the paper's value model (:mod:`.controller`, MFG and HJB_d banks);
:mod:`.params` declares every parameter with its unit. Guidance composes with the safety layer:
the nominal acceleration goes through :mod:`mfg_autopilot.safety` before it becomes a setpoint.
May import :mod:`mfg_autopilot.paper`, :mod:`mfg_autopilot.safety`, :mod:`mfg_autopilot.mission` and
:mod:`mfg_autopilot.interface`; never the runtime (no I/O here).
"""
