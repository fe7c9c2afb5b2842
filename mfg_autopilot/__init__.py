"""The onboard controller: one process per vehicle computes acceleration setpoints (docs/architecture.md).

Rooms, from the bottom up (each sub-package's docstring says what it may import; import-linter
holds the rules, see ``[tool.importlinter]`` in pyproject.toml):

- :mod:`~mfg_autopilot.interface`: the typed values between a controller and its caller.
- :mod:`~mfg_autopilot.paper`: the paper's model and Algorithms 3 and 4, equation numbers in names.
- :mod:`~mfg_autopilot.mission`: missions (geodetic, validated) and the shared swarm frame.
- :mod:`~mfg_autopilot.safety`: what keeps vehicles apart whatever guidance asks (the backstop).
- :mod:`~mfg_autopilot.guidance`: the product controller (the ``default`` preset): plan, slots,
  goal and interaction terms, composed with the safety layer.
- :mod:`~mfg_autopilot.pde`: Algorithms 1 and 2, the PDEs solved on a grid (the reference).
- :mod:`~mfg_autopilot.presets`: which controller a (preset, mode) pair names.
- :mod:`~mfg_autopilot.runtime`: the per-vehicle process: MAVLink link, Zenoh exchange, router,
  CLI. The only room that does I/O.
"""
