"""Which controller a (preset, mode) pair names: the one table every entry point reads.

The simulator (``mfg-swarm sim``), the vehicle process (``mfg-autopilot``) and the launcher build
their controllers here, so a preset means the same everywhere. Built-in presets:

- ``default``: the product controller (:mod:`mfg_autopilot.guidance`, with :mod:`mfg_autopilot.safety`);
- ``paper`` / ``paper-lqr``: the paper's Algorithms 3 and 4 (:mod:`mfg_autopilot.paper`), the latter
  warm-started from the LQR value; in the ``*-pde`` modes, Algorithms 1 and 2 (:mod:`mfg_autopilot.pde`).

The ``orca`` mode (``default`` preset) is the baseline the MFG controller is compared against:
ORCA on the proximity sensor's neighbours, no communication (:mod:`mfg_autopilot.safety.orca`).

A new controller is added with :func:`register` (see docs/architecture.md). This module sits
above the controller rooms (it imports them) and below the runtime (which imports it); the
rooms it loads are imported on first use, so a process pays only for the controller it flies.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from mfg_autopilot.interface import Controller
from mfg_autopilot.paper.params import PAPER, PAPER_LQR, Preset

__all__ = ["MODES", "DEFAULT_PRESET_NAME", "preset_by_name", "make_controller", "register", "warm_up"]

MODES = ("mfg", "hjb", "mfg-pde", "hjb-pde", "orca")
"""mfg / hjb: the learned controllers (Algorithms 4 / 3); *-pde: the solved ones (2 / 1); orca: the
communication-free reciprocal-collision-avoidance baseline (``default`` preset only; safety/orca.py)."""

DEFAULT_PRESET_NAME = "default"
"""The preset every entry point flies unless told otherwise."""

Factory = Callable[[Preset, np.ndarray], Controller]


def _paper(mode: str) -> Factory:
    from mfg_autopilot.paper.controllers import PaperHJBController, PaperMFGController

    return {"hjb": PaperHJBController, "mfg": PaperMFGController}[mode]


def _pde(mode: str) -> Factory:
    from mfg_autopilot.pde.control import HJBPDEController, MFGPDEController

    return {"hjb-pde": HJBPDEController, "mfg-pde": MFGPDEController}[mode]


def _default(mode: str) -> Factory:
    from mfg_autopilot.guidance.controller import DefaultHJBController, DefaultMFGController

    return {"hjb": DefaultHJBController, "mfg": DefaultMFGController}[mode]


def _orca() -> Factory:
    from mfg_autopilot.safety.orca import OrcaController

    return OrcaController


def _default_preset() -> Preset:
    from mfg_autopilot.guidance.params import DEFAULT

    return DEFAULT


_PRESETS: dict[str, Callable[[], Preset]] = {"paper": lambda: PAPER, "paper-lqr": lambda: PAPER_LQR,
                                            "default": _default_preset}
_FACTORIES: dict[tuple[str, str], Callable[[], Factory]] = {
    ("paper", "hjb"): lambda: _paper("hjb"), ("paper", "mfg"): lambda: _paper("mfg"),
    ("paper-lqr", "hjb"): lambda: _paper("hjb"), ("paper-lqr", "mfg"): lambda: _paper("mfg"),
    ("paper", "hjb-pde"): lambda: _pde("hjb-pde"), ("paper", "mfg-pde"): lambda: _pde("mfg-pde"),
    ("default", "hjb"): lambda: _default("hjb"), ("default", "mfg"): lambda: _default("mfg"),
    ("default", "orca"): _orca,
}


def register(preset: Preset, mode: str, factory: Factory) -> None:
    """Make ``preset`` (by its name) and its controller ``factory(preset, destination_site_m)`` for
    ``mode`` known to every entry point. Re-registering a name replaces it."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    _PRESETS[preset.name] = lambda: preset
    _FACTORIES[(preset.name, mode)] = lambda: factory


def preset_by_name(name: str) -> Preset:
    """The preset called ``name`` (ValueError naming the known ones otherwise)."""
    try:
        return _PRESETS[name]()
    except KeyError:
        raise ValueError(f"unknown preset {name!r} (known: {', '.join(sorted(_PRESETS))})") from None


def with_inner_loop(preset: Preset, on: bool = True) -> Preset:
    """``preset`` with its telemetry-rate inner loop switched on (or off): ``TrackingParams.inner_loop``
    (guidance/inner_loop.py; on in the default guidance's presets). ValueError for switching it on in a preset without
    the default guidance's tracking (the paper's); switching it off there is a no-op."""
    tracking = getattr(preset, "tracking", None)
    if tracking is None:
        if not on:
            return preset
        raise ValueError(f"preset {preset.name!r} has no inner loop (only the default guidance's presets do)")
    return replace(preset, tracking=replace(tracking, inner_loop=on))


def with_acc_lag(preset: Preset, acc_lag_s: float) -> Preset:
    """``preset`` whose own-vehicle model assumes the airframe's acceleration lag ``acc_lag_s`` (TrackingParams.acc_lag_s:
    the escape's prediction of its own swerve, safety.backstop.OwnModel). A preset without the default guidance's
    tracking (the paper's) has no such model: returned as it is."""
    tracking = getattr(preset, "tracking", None)
    if tracking is None or tracking.acc_lag_s == float(acc_lag_s):
        return preset
    return replace(preset, tracking=replace(tracking, acc_lag_s=float(acc_lag_s)))


def inner_loop_on(preset: Preset, override: bool | None = None) -> bool:
    """Whether ``preset`` flies the telemetry-rate inner loop: ``override`` if given (``with_inner_loop``'s checks),
    else its ``TrackingParams.inner_loop`` (False for a preset without the default guidance's tracking)."""
    if override is not None:
        preset = with_inner_loop(preset, override)
    return bool(getattr(getattr(preset, "tracking", None), "inner_loop", False))


def make_controller(mode: str, preset: Preset, destination_site_m: np.ndarray) -> Controller:
    """The controller bank for a mode and preset; one row per bank vehicle,
    ``destination_site_m`` (n, 2) being each row's mission destination site."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    try:
        factory = _FACTORIES[(preset.name, mode)]()
    except KeyError:
        raise ValueError(f"no controller for preset {preset.name!r} in mode {mode!r}") from None
    return factory(preset, destination_site_m)


def warm_up() -> None:
    """Load (or, on a cold cache, compile) every numba kernel a control step can reach (the paper's
    feature and learner kernels, the backstop's, the orca mode's), so that the first control step does not pay for it."""
    from mfg_autopilot.paper import kernels
    from mfg_autopilot.safety import backstop, orca

    kernels.warm_up()
    backstop.warm_up()
    orca.warm_up()
