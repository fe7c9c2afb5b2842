"""`mfg-swarm plot`: the figures are written from a run folder, and Fig. 3's close-up appears
only when the swarm is small on the plot."""

import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mfg_swarm.plots import _zoom_inset  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_plot_command_writes_fig3_and_fig4_from_a_sim_folder(tmp_path):
    out = tmp_path / "run"
    for cmd in (["sim", "--n", "4", "--steps", "20", "--out", str(out), "--no-progress"], ["plot", str(out)]):
        p = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", *cmd], capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
    for name in ("fig3_trajectories.png", "fig4_regularizer.png"):
        data = (out / name).read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 5000, name


def test_zoom_inset_only_for_a_swarm_small_on_the_plot():
    dest = np.zeros((4, 2))
    fig, (a, b) = plt.subplots(1, 2)
    compact = np.array([[150.0, 100.0], [151.5, 100.0], [150.0, 101.5], [151.5, 101.5]])
    _zoom_inset(a, compact, dest, [], extent_m=150.0)
    spread = np.array([[0.0, 0.0], [150.0, 100.0], [75.0, 50.0], [10.0, 10.0]])
    _zoom_inset(b, spread, dest, [], extent_m=150.0)
    assert len(a.child_axes) == 1 and len(b.child_axes) == 0
    ins = a.child_axes[0]
    lo, hi = ins.get_ylim()                        # x (north) on the vertical axis, to scale around the swarm
    assert lo < 150.0 and hi > 151.5 and hi - lo < 5.0
    plt.close(fig)
