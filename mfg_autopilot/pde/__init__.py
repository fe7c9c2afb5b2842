"""Algorithms 1 and 2: the HJB and FPK equations solved on a grid (the reference the learners approximate).

:mod:`.solver` discretises eqs. 6-10 per axis (finite differences, implicit time stepping);
:mod:`.control` wraps the solutions as controller banks (modes ``hjb-pde`` / ``mfg-pde``).
May import :mod:`mfg_autopilot.paper` and :mod:`mfg_autopilot.interface` only; no I/O.
"""
