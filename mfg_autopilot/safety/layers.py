"""Which of the default controllers' safety layers made a command: one bit per layer (:class:`Layer`), recorded per
UAV and step (the simulator's ``backstop_layer``, the controller log's step record, flight.mcap's setpoints; see
docs/formats.md). Kept apart from :mod:`mfg_autopilot.safety.backstop` so that the swarm tools that only read the bits
(recording, live view) do not import the compiled kernels."""

from __future__ import annotations

import enum

import numpy as np

__all__ = ["Layer", "layer_names", "counts_by_layer"]


class Layer(enum.IntFlag):
    """Which of the default controllers' safety layers made a row's command this step (one bit each; 0: none acted, the
    nominal command flew). A row's bits name the layers whose output is in the command it sent: an escape replaces
    the half-plane pushes and a crowded row's barrier filter replaces them too, so those rows carry that one bit (plus
    LAST_CBF where the last layer filtered the result). Recorded per UAV and step by the simulator (``backstop_layer``,
    docs/formats.md)."""

    PLANNED = 1     # the planned vehicles' reciprocal half-plane push (backstop_acc over the planned entries)
    ESCAPE = 2      # escape_acc: a sampled swerve from vehicles off the plan (and the yield, and the gap escape)
    CROWD_CBF = 4   # cbf_acc for a crowded row (most of what it senses is off the plan)
    LAST_CBF = 8    # cbf_acc as the last layer over the other commands (BackstopParams.cbf_last_layer)
    GAP = 16        # the gap push (BackstopParams.gap_push)
    PUSH = 32       # the crowded rows' half-plane push (when crowd_cbf is off)


def layer_names(bits: int) -> str:
    """A row's Layer bits by name, lower case, joined by '+' in bit order ('escape', 'crowd_cbf+last_cbf'); '-' for
    none (the nominal command flew)."""
    names = [layer.name.lower() for layer in Layer if int(bits) & int(layer)]
    return "+".join(names) if names else "-"


def counts_by_layer(bits: np.ndarray) -> dict[str, int]:
    """How many entries of ``bits`` (any shape of Layer bits, e.g. the (T, N) ``backstop_layer``) carry each layer, by
    its lower-case name (metrics.json's ``safety_interventions_by_layer``). A row filtered twice counts under both."""
    bits = np.asarray(bits, dtype=np.uint8)
    return {layer.name.lower(): int(np.count_nonzero(bits & np.uint8(layer))) for layer in Layer}
