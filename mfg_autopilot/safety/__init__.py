"""What keeps vehicles apart whatever guidance asks: the communication-free proximity backstop.

:mod:`.backstop` turns what the onboard proximity sensor sees into a correction of the nominal
acceleration (a half-plane push against planned vehicles, a sampled escape against vehicles off
the plan); :mod:`.kernels` holds its numba kernels, :mod:`.params` its parameters. May import
:mod:`mfg_autopilot.paper` (the vehicle model and caps) and :mod:`mfg_autopilot.interface`;
never guidance (safety must not depend on what it guards against) nor the runtime.
"""
