"""Fig. 3 of Tchuiev et al. (2019): (a) the map and one ground-truth track, (b) the sampled tracks.

The paper's setup (Sec. V): 6 objects of one class in a perceptually aliased layout, every
track starting at the same pose. The paper does not publish its map; ours is
:class:`hybridslam.PaperSetup` (two rows of three objects). Prints the map and track statistics.

    python experiments/fig3_scenario.py [-o runs/figures] [--tracks 50] [--steps 10]
"""

from __future__ import annotations

import argparse
import os

import numpy as np
from matplotlib.figure import Figure

import hybridslam as hs
from hybridslam.analysis.plot import plot_map


hs.setup()  # float64 and XLA's CPU thread pool, before any array (hybridslam.config)

def main(output: str = os.path.join("runs", "figures"), tracks: int = 50, steps: int = 10, seed: int = 0) -> str:
    """Draw Fig. 3 (a, b) into ``output/fig3_scenario.png``; return the path."""
    scenarios = [hs.simulate(seed + t, steps=steps) for t in range(tracks)]
    fig = Figure(figsize=(12, 4.8), layout="constrained")
    ax_a, ax_b = fig.subplots(1, 2, sharex=True, sharey=True)
    plot_map(ax_a, scenarios[0])
    poses = np.asarray(scenarios[0].true_robot_poses)
    ax_a.quiver(poses[:, 0], poses[:, 1], np.cos(poses[:, 2]), np.sin(poses[:, 2]), color="g",
                angles="xy", scale_units="xy", scale=2.0, width=0.004, label="camera heading")
    ax_a.set_title("(a) map (objects O0-O5, true orientation arrows) and one ground-truth track", fontsize=10)
    ax_a.legend(fontsize=8, loc="lower left")
    plot_map(ax_b, scenarios[0], trajectory=False)
    for t, s in enumerate(scenarios):
        p = np.asarray(s.true_robot_poses)
        ax_b.plot(p[:, 0], p[:, 1], "-", color=f"C{t % 10}", lw=0.9, alpha=0.8)
    ax_b.plot(*scenarios[0].true_robot_poses[0, :2], "k^", ms=8, label="common start")
    ax_b.set_title(f"(b) {tracks} sampled tracks of {steps} steps", fontsize=10)
    ax_b.legend(fontsize=8, loc="lower left")
    for ax in (ax_a, ax_b):
        ax.set_aspect("equal", adjustable="box")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("x [m]")
    ax_a.set_ylabel("y [m]")
    os.makedirs(output, exist_ok=True)
    path = os.path.join(output, "fig3_scenario.png")
    fig.savefig(path, dpi=120)

    setup = hs.PaperSetup()
    print("objects (x, y, theta) prior means:")
    for n, pose in enumerate(setup.object_poses):
        print(f"  O{n}: {pose[0]:6.2f} {pose[1]:6.2f} {pose[2]:6.2f}")
    ends = np.stack([s.true_robot_poses[-1, :2] for s in scenarios])
    dets = np.array([sum(len(st.detections) for st in s.steps) for s in scenarios])
    print(f"{tracks} tracks of {steps} steps from {setup.start}: end x in [{ends[:, 0].min():.1f}, "
          f"{ends[:, 0].max():.1f}] m, end y in [{ends[:, 1].min():.1f}, {ends[:, 1].max():.1f}] m; "
          f"detections per track: mean {dets.mean():.1f}, min {dets.min()}, max {dets.max()}")
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", default=os.path.join("runs", "figures"))
    parser.add_argument("--tracks", type=int, default=50)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    a = parser.parse_args()
    main(a.output, a.tracks, a.steps, a.seed)
