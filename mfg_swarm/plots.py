"""The paper's figures from run folders (`mfg-swarm plot`), as PNG.

- Fig. 3: trajectory snapshots of the swarm at several times, and the HJB weights w_H of a
  reference UAV over time (``fig3_trajectories.png``).
- Fig. 4: accumulated regulariser activations over time (``fig4_regularizer.png``; one
  curve per run when given several).
- Fig. 5: communication, computation and motion energy per UAV normalised by HJB_1's,
  across N (``fig5_energy.png``; needs runs of HJB_1 and the others at several N).

A run folder holds metrics.json and trajectories.npz (docs/formats.md).
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .results import load_trajectories  # noqa: E402

__all__ = ["plot_run", "plot_regularizer", "plot_energy", "run_label", "find_runs"]


def run_label(m: dict) -> str:
    if str(m.get("mode", "")).startswith("hjb"):
        d = m.get("range_m")
        return f"HJB_{d:g}" if d is not None else "HJB"
    return "MFG"


def find_runs(root: Path) -> list[Path]:
    """Run folders at or below root (those holding metrics.json and trajectories.npz)."""
    root = Path(root)
    return sorted(p.parent for p in root.rglob("metrics.json") if (p.parent / "trajectories.npz").exists())


def _zoom_inset(ax, pos_k_m: np.ndarray, dest_m: np.ndarray, hit: list[int], extent_m: float) -> None:
    """A to-scale close-up of the swarm at one snapshot (a 9-UAV swarm is a dot on a 150 m plot).
    Drawn only when the swarm spans less than a fifth of the whole plot."""
    ok = np.all(np.isfinite(pos_k_m), axis=1)
    if not np.any(ok):
        return
    p = pos_k_m[ok]
    lo, hi = p.min(axis=0), p.max(axis=0)
    span = max(float(np.max(hi - lo)), 2.0)
    if span > 0.2 * extent_m:
        return
    c, half = 0.5 * (lo + hi), 0.6 * span
    ins = ax.inset_axes([0.58, 0.04, 0.40, 0.40])
    ins.scatter(pos_k_m[:, 1], pos_k_m[:, 0], s=5, color="C0", zorder=3)
    if hit:
        ins.scatter(pos_k_m[hit, 1], pos_k_m[hit, 0], s=6, color="C3", zorder=4)
    ins.scatter(dest_m[:, 1], dest_m[:, 0], marker="x", s=6, color="k", zorder=2)
    ins.set_xlim(c[1] - half, c[1] + half)
    ins.set_ylim(c[0] - half, c[0] + half)
    ins.set_aspect("equal")
    ins.tick_params(labelsize=5, length=2, pad=1)
    ins.set_title(f"{2 * half:.0f} m", fontsize=6, pad=1)


def plot_run(run_dir: Path, n_snapshots: int = 4) -> list[Path]:
    """Fig. 3 and Fig. 4 for one run; returns the PNG paths."""
    run_dir = Path(run_dir)
    m = json.loads((run_dir / "metrics.json").read_text())
    traj = load_trajectories(run_dir / "trajectories.npz")
    T1 = traj.pos_m.shape[0]
    idx = np.unique(np.linspace(0, T1 - 1, n_snapshots).round().astype(int))
    ncols = len(idx) + (1 if traj.w_H_ref is not None else 0)
    fig, axes = plt.subplots(1, ncols, figsize=(3.2 * ncols, 3.4), squeeze=False)
    axes = axes[0]
    pos = traj.pos_m
    lo, hi = np.nanmin(pos, axis=(0, 1)), np.nanmax(pos, axis=(0, 1))
    pad = 0.05 * max(float(np.max(hi - lo)), 1.0)
    collided = {tuple(p) for p in m.get("collided_pairs_list", [])}
    hit = sorted({i for p in collided for i in p})
    for ax, k in zip(axes, idx):
        ax.plot(pos[: k + 1, :, 1], pos[: k + 1, :, 0], lw=0.5, color="0.75")
        ax.scatter(pos[k, :, 1], pos[k, :, 0], s=8, color="C0", zorder=3)
        if hit:
            ax.scatter(pos[k, hit, 1], pos[k, hit, 0], s=10, color="C3", zorder=4)
        ax.scatter(traj.dest_m[:, 1], traj.dest_m[:, 0], marker="x", s=12, color="k", zorder=2)
        ax.set_title(f"t = {traj.t_s[k]:.0f} s", fontsize=9)
        _zoom_inset(ax, pos[k], traj.dest_m, hit, extent_m=float(np.max(hi - lo)))
        ax.set_xlim(lo[1] - pad, hi[1] + pad)
        ax.set_ylim(lo[0] - pad, hi[0] + pad)
        ax.set_xlabel("y (east), m", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("x (north), m", fontsize=8)
    cp = m.get("closest_pair")
    if cp is not None:
        # the closest pair of the flight: both tracks, and where they came closest, in the snapshot nearest that step
        i, j, kc = (int(v) for v in cp)
        ax = axes[int(np.argmin(np.abs(idx - kc)))]
        for u in (i, j):
            ax.plot(pos[:, u, 1], pos[:, u, 0], lw=0.9, color="C1", zorder=4)
        mid = 0.5 * (pos[kc, i] + pos[kc, j])
        ax.scatter([mid[1]], [mid[0]], marker="o", s=60, facecolors="none", edgecolors="C1", zorder=5,
                   label=f"closest: {m.get('min_separation_m', float('nan')):.2f} m (UAVs {i}, {j}, t = {traj.t_s[kc]:.0f} s)")
        ax.legend(fontsize=6, loc="lower left")
    if traj.w_H_ref is not None:
        ax = axes[-1]
        ax.plot(np.arange(traj.w_H_ref.shape[0]) * traj.dt_s, traj.w_H_ref, lw=0.6)
        ax.set_title("w_H of UAV 0", fontsize=9)
        ax.set_xlabel("t, s", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.suptitle(f"{run_label(m)}, N = {m['n']}, preset {m.get('preset', '?')}: {m['collision_pairs']} collided pairs, "
                 f"{100 * m['arrived_fraction']:.0f} % arrived ({m.get('path', 'sim')})", fontsize=9)
    fig.tight_layout()
    p3 = run_dir / "fig3_trajectories.png"
    fig.savefig(p3, dpi=110)
    plt.close(fig)
    return [p3, plot_regularizer([run_dir], run_dir / "fig4_regularizer.png")]


def plot_regularizer(run_dirs: list[Path], out_png: Path) -> Path:
    """Fig. 4: accumulated number of R_i(t) > 0 (summed over UAVs) against time."""
    fig, ax = plt.subplots(figsize=(5, 3.4))
    for d in run_dirs:
        m = json.loads((Path(d) / "metrics.json").read_text())
        traj = load_trajectories(Path(d) / "trajectories.npz")
        acc = np.cumsum(traj.reg_active.sum(axis=1))
        ax.plot(np.arange(1, acc.size + 1) * traj.dt_s, acc, label=f"{run_label(m)}, N = {m['n']}")
    ax.set_xlabel("t, s")
    ax.set_ylabel("accumulated R activations")
    if ax.get_lines():
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return Path(out_png)


def plot_energy(metrics: list[dict], out_png: Path, title: str = "") -> Path | None:
    """Fig. 5: per-UAV energies normalised by HJB_1's at the same N (means over seeds)."""
    by = defaultdict(lambda: defaultdict(list))
    for m in metrics:
        by[run_label(m)][m["n"]].append(m)
    ref = next((k for k in by if k.startswith("HJB_1") and k in ("HJB_1", "HJB_0.707107")), None)
    if ref is None:
        return None
    keys = [("comm_states_per_uav", "communication"), ("grad_evals_per_uav", "computation"), ("motion_energy_per_uav", "motion")]
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4))
    for ax, (key, name) in zip(axes, keys):
        ref_zero = all(m[key] == 0 for ms in by[ref].values() for m in ms)
        for label in sorted(by):
            if label == ref:
                continue
            ns = sorted(n for n in by[label] if n in by[ref])
            ratio = []
            for n in ns:
                r = np.mean([m[key] for m in by[ref][n]])
                v = np.mean([m[key] for m in by[label][n]])
                ratio.append(v if ref_zero else (v / r if r > 0 else np.nan))
            if ref_zero and not np.any(np.asarray(ratio) > 0):
                continue
            ax.plot(ns, ratio, marker="o", label=label)
        # normalised by HJB_1 as in Fig. 5, unless HJB_1 spends none of it (then per UAV, absolute)
        ax.set_title(f"{name} per UAV ({ref} spends none)" if ref_zero else f"{name} energy / {ref}", fontsize=9)
        ax.set_xlabel("N")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return Path(out_png)
