"""Every entry point flies the same controller unless told otherwise (issue 19, item 6)."""

from __future__ import annotations

from mfg_autopilot.presets import DEFAULT_PRESET_NAME, preset_by_name
from mfg_autopilot.runtime import cli as autopilot_cli
from mfg_autopilot.runtime.config import AutopilotConfig
from mfg_swarm import cli as swarm_cli


def test_given_no_preset_flag_when_each_entry_point_parses_then_all_fly_the_default_preset():
    swarm = swarm_cli.build_parser()
    assert swarm.parse_args(["sim", "--out", "x"]).preset == DEFAULT_PRESET_NAME
    assert swarm.parse_args(["run"]).preset == DEFAULT_PRESET_NAME
    assert autopilot_cli.build_parser().parse_args(["--instance", "0", "--n", "1"]).preset == DEFAULT_PRESET_NAME
    assert AutopilotConfig(instance=0, connect="udpin:127.0.0.1:14540", mode="mfg").preset == DEFAULT_PRESET_NAME


def test_the_default_preset_is_the_product_controller():
    assert DEFAULT_PRESET_NAME == "default"
    assert preset_by_name(DEFAULT_PRESET_NAME).name == "default"
