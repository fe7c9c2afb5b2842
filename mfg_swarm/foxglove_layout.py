"""The Foxglove layout for flight.mcap (docs/foxglove_layout.json): map, 3D scene, plots, log.

Built with the Foxglove SDK's layout types (``foxglove.layouts``), so its fields are the ones Foxglove
reads. Left: the map (every /uav<i>/fix, following UAV 0) over the 3D scene (/swarm/scene, frame
``swarm_enu``). Right: the swarm's minimum separation and arrivals, each UAV's acceleration setpoint
(north and east), then the event log (/log: collisions, backstop interventions).

    python -m mfg_swarm.foxglove_layout --n 9 --out docs/foxglove_layout.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["build_layout", "layout_json", "DEFAULT_N"]

DEFAULT_N = 9
"""Vehicles given a setpoint series in docs/foxglove_layout.json (`./dev run`'s swarm); more add no series but are on
the map and in the scene."""


def build_layout(n: int = DEFAULT_N):
    """The layout (``foxglove.layouts.Layout``) for a recording of ``n`` vehicles."""
    import foxglove.layouts as fl

    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    fixes = [f"/uav{i}/fix" for i in range(n)]
    map_panel = fl.MapPanel(title="swarm on the map", config=fl.MapConfig(
        follow_topic=fixes[0], zoom_level=19,
        topic_config={t: fl.MapTopicSettings(history_mode="all", show_velocity=True) for t in fixes}))
    scene = fl.ThreeDeePanel(title="3D: safety spheres, velocity, slots, closest pair", config=fl.ThreeDeeConfig(
        follow_tf="swarm_enu", topics={"/swarm/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True)}))
    separation = fl.PlotPanel(title="separation and arrivals", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value="/swarm/separation.min_separation_m", label="min separation, m"),
        fl.PlotSeries(value="/swarm/separation.arrived", label="UAVs in their slot"),
        fl.PlotSeries(value="/swarm/separation.collided_pairs_so_far", label="collided pairs"),
    ], show_legend=True, x_axis_label="t", y_axis_label="m / count"))
    setpoints = fl.PlotPanel(title="acceleration setpoints", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"/uav{i}/setpoint.acc_{axis}_m_s2", label=f"UAV {i} {axis}")
        for i in range(n) for axis in ("north", "east")], show_legend=True, y_axis_label="m/s^2"))
    log = fl.LogPanel(title="events", config=fl.LogConfig(topic_to_render="/log"))
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=1, content=map_panel), fl.SplitItem(proportion=1, content=scene)])),
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=1, content=separation), fl.SplitItem(proportion=1, content=setpoints),
            fl.SplitItem(proportion=0.6, content=log)])),
    ]))


def layout_json(n: int = DEFAULT_N) -> str:
    """The layout as the indented JSON of docs/foxglove_layout.json."""
    return json.dumps(json.loads(build_layout(n).to_json()), indent=1) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mfg_swarm.foxglove_layout", description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=DEFAULT_N, help=f"vehicles with a setpoint series (default: {DEFAULT_N})")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    args.out.write_text(layout_json(args.n))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
