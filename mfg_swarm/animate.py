"""Animated replay of a run (`mfg-swarm plot --animate RUN_DIR`): flight.gif, and flight.mp4 if asked and ffmpeg exists.

One frame per control step (every k-th step when the flight has more than ``max_frames`` instants:
k = ceil((T + 1) / max_frames), the last instant always included). Each frame shows the swarm in the
swarm frame (north up, east right), every UAV's track so far, the destination slots, the closest pair
of that instant (red), a close-up that follows that pair, and the time, the minimum separation (now and
so far, between instants) and how many UAVs are in their slot (within 1 m, metrics.ARRIVAL_TOLERANCE_M).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FFMpegWriter, FuncAnimation, PillowWriter  # noqa: E402

from . import metrics as M  # noqa: E402
from .results import load_trajectories  # noqa: E402

__all__ = ["animate_run", "frame_steps"]


def frame_steps(n_instants: int, max_frames: int) -> np.ndarray:
    """The control steps drawn: every k-th of 0..n_instants-1 with k = ceil(n_instants / max_frames), plus the last."""
    if max_frames < 2:
        raise ValueError(f"max_frames must be >= 2, got {max_frames}")
    k = max(1, math.ceil(n_instants / max_frames))
    idx = np.arange(0, n_instants, k)
    if idx[-1] != n_instants - 1:
        idx = np.append(idx, n_instants - 1)
    return idx


def animate_run(run_dir: Path, *, fps: float = 10.0, max_frames: int = 200, mp4: bool = False, dpi: int = 80) -> list[Path]:
    """Write run_dir/flight.gif (and flight.mp4 with ``mp4`` when ffmpeg is on the PATH); returns the paths."""
    run_dir = Path(run_dir)
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    m = json.loads((run_dir / "metrics.json").read_text())
    traj = load_trajectories(run_dir / "trajectories.npz")
    pos, dest, dt = traj.pos_m, traj.dest_m, traj.dt_s
    T1, n, _ = pos.shape
    steps = frame_steps(T1, max_frames)
    dist = np.linalg.norm(pos - dest[None], axis=2)
    inside = dist <= M.ARRIVAL_TOLERANCE_M
    dmin = np.full(T1, np.inf)
    pair = np.full((T1, 2), -1)
    if n > 1:
        iu = np.triu_indices(n, 1)
        for k in range(T1):
            d = np.linalg.norm(pos[k][:, None] - pos[k][None], axis=2)[iu] if n <= 400 else None
            if d is None:
                from scipy.spatial import cKDTree
                dd, ii = cKDTree(pos[k]).query(pos[k], k=2)
                a = int(np.argmin(dd[:, 1])); dmin[k] = dd[a, 1]; pair[k] = (a, ii[a, 1])
            else:
                a = int(np.argmin(d)); dmin[k] = d[a]; pair[k] = (iu[0][a], iu[1][a])
    dmin_so_far = np.minimum.accumulate(dmin)

    fin = np.isfinite(pos).all(axis=2)
    allp = np.concatenate([pos[fin], dest])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    pad = 0.06 * max(float(np.max(hi - lo)), 1.0)
    span = 0.5 * float(np.max(hi - lo)) + pad           # a square overview: equal aspect fills the axes
    mid = 0.5 * (lo + hi)
    lo, hi, pad = mid - span, mid + span, 0.0
    # the close-up follows the closest pair of each instant (its midpoint), at a fixed width: four times the largest
    # per-instant minimum separation, at least 3 m
    finite_d = dmin[np.isfinite(dmin)]
    half = 0.5 * max(3.0, 4.0 * float(finite_d.max()) if finite_d.size else 3.0)
    centre = np.full((T1, 2), np.nan)
    ok = pair[:, 0] >= 0
    centre[ok] = 0.5 * (pos[ok, pair[ok, 0]] + pos[ok, pair[ok, 1]])
    zoom = 2 * half < 0.2 * 2 * span     # a close-up only where the overview cannot show the pair
    fig, axes = plt.subplots(1, 2 if zoom else 1, figsize=(8.0 if zoom else 4.6, 4.6), squeeze=False)
    ax, zx = axes[0, 0], (axes[0, 1] if zoom else None)
    if zoom:
        zx.set_aspect("equal")
        zx.set_xlabel("y (east), m")
        zx.set_title(f"close-up on the closest pair, {2 * half:.0f} m wide", fontsize=9)
        zx.scatter(dest[:, 1], dest[:, 0], marker="x", s=14, color="k", zorder=2)
    ax.set_xlim(lo[1] - pad, hi[1] + pad)
    ax.set_ylim(lo[0] - pad, hi[0] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("y (east), m")
    ax.set_ylabel("x (north), m")
    ax.scatter(dest[:, 1], dest[:, 0], marker="x", s=14, color="k", zorder=2, label="slots")
    colours = plt.get_cmap("tab10")(np.arange(n) % 10)
    trails = [ax.plot([], [], lw=0.6, color=colours[i], alpha=0.6)[0] for i in range(n)]
    dots = ax.scatter(pos[0, :, 1], pos[0, :, 0], s=16, c=colours, zorder=3)
    link, = ax.plot([], [], color="C3", lw=1.5, zorder=4)
    zdots = zx.scatter(pos[0, :, 1], pos[0, :, 0], s=16, c=colours, zorder=3) if zoom else None
    zlink = zx.plot([], [], color="C3", lw=1.5, zorder=4)[0] if zoom else None
    ztrails = [zx.plot([], [], lw=0.6, color=colours[i], alpha=0.6)[0] for i in range(n)] if zoom else []
    text = fig.text(0.5, 0.925, "", va="top", ha="center", fontsize=8, family="monospace")
    fig.suptitle(f"{m.get('scenario', '')} {m.get('mode', '')}, N = {n} ({m.get('path', 'sim')}): the closest pair in red",
                 fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.85))

    def draw(k: int):
        for i, ln in enumerate(trails):
            ln.set_data(pos[: k + 1, i, 1], pos[: k + 1, i, 0])
        dots.set_offsets(np.column_stack([pos[k, :, 1], pos[k, :, 0]]))
        for i, ln in enumerate(ztrails):
            ln.set_data(pos[: k + 1, i, 1], pos[: k + 1, i, 0])
        if zoom:
            zdots.set_offsets(np.column_stack([pos[k, :, 1], pos[k, :, 0]]))
        if zoom and np.all(np.isfinite(centre[k])):    # the closest pair's midpoint
            zx.set_xlim(centre[k, 1] - half, centre[k, 1] + half)
            zx.set_ylim(centre[k, 0] - half, centre[k, 0] + half)
        if pair[k, 0] >= 0:
            i, j = pair[k]
            link.set_data([pos[k, i, 1], pos[k, j, 1]], [pos[k, i, 0], pos[k, j, 0]])
            if zoom:
                zlink.set_data([pos[k, i, 1], pos[k, j, 1]], [pos[k, i, 0], pos[k, j, 0]])
        text.set_text(f"t = {k * dt:5.1f} s (step {k}/{T1 - 1})   in slot {int(inside[k].sum())}/{n}\n"
                      f"min separation {dmin[k]:5.2f} m (so far {dmin_so_far[k]:5.2f} m)")
        return [*trails, dots, link, text, *ztrails] + ([zdots, zlink] if zoom else [])

    anim = FuncAnimation(fig, draw, frames=[int(k) for k in steps], blit=False)
    out = [run_dir / "flight.gif"]
    tmp = run_dir / ".flight.gif.tmp.gif"
    try:
        anim.save(tmp, writer=PillowWriter(fps=fps), dpi=dpi)
        tmp.replace(out[0])
        if mp4:
            if shutil.which("ffmpeg") is None:
                raise ValueError("--mp4 needs ffmpeg on the PATH (flight.gif was written)")
            anim.save(run_dir / "flight.mp4", writer=FFMpegWriter(fps=fps), dpi=dpi)
            out.append(run_dir / "flight.mp4")
    finally:
        plt.close(fig)
        if tmp.exists():
            tmp.unlink()
    return out
