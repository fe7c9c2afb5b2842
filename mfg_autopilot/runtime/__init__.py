"""The per-vehicle process: the only room of the controller that does I/O.

:mod:`.autopilot` runs one vehicle's control loop (MAVLink link through :mod:`mavlink_bridge`,
observation, controller step, setpoint, controller log, checkpoints); :mod:`.exchange` is the
Zenoh boundary (the t = 0 swarm-state exchange and HJB_d's per-step gossip), :mod:`.router` a
Zenoh router process, :mod:`.cli` the ``mfg-autopilot`` command (configuration read once, here).
May import every other room and :mod:`mavlink_bridge`; the only place in the project that
imports ``zenoh``.
"""
