"""Plots and the HTML report of a ``symbio run`` / ``symbio demo`` output folder.

* ``trajectory_top.png``: top view (the two axes the ground truth spreads over most) of the ground
  truth, the odometry and the loop-closed trajectory, both Sim(3)-aligned to the ground truth
  (evo), with the accepted loops as green edges between the loop-closed keyframes.
* ``ape_over_time.png``: evo APE (translation) per frame, odometry vs loop-closed.
* ``report.html``: the metrics, the plots, the loops table and the run's configuration.

Without ground truth the trajectories are shown unaligned and the APE plot is left out.
"""

from __future__ import annotations

import contextlib
import html
import io
import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from evo.core import metrics
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D

from eval.outputs import RunFolder
from frontends.datasets import Dataset
from frontends.errors import display_path
from slam_backend.pipeline import LoopRecord

TOP_VIEW_FILE = "trajectory_top.png"
APE_FILE = "ape_over_time.png"
REPORT_FILE = "report.html"

Poses = Sequence[tuple[int, float, np.ndarray]]
_MODES = {(0, 1): "xy", (0, 2): "xz", (1, 2): "yz"}


def _pyplot() -> tuple[Any, Any]:
    """matplotlib's pyplot (Agg) and evo's plot module, imported when a plot is drawn: with
    seaborn and pandas they hold about 130 MB, which a run would otherwise carry from its start
    through its memory peak (the global bundle adjustment)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from evo.tools import plot as evo_plot

    return plt, evo_plot


def _trajectory(poses: Poses) -> PoseTrajectory3D:
    return PoseTrajectory3D(
        poses_se3=[p for _, _, p in poses], timestamps=np.array([t for _, t, _ in poses], dtype=np.float64)
    )


def with_ground_truth(dataset: Dataset, poses: Poses) -> tuple[Poses, PoseTrajectory3D | None]:
    """The posed frames that have GT, and the GT trajectory of exactly those frames (None without
    GT or with fewer than three such frames: a similarity needs three non-collinear positions)."""
    if dataset.gt_poses is None:
        return [], None
    kept = [p for p in poses if np.isfinite(dataset.gt_poses[p[0]]).all()]
    if len(kept) < 3:
        return kept, None
    gt = PoseTrajectory3D(
        poses_se3=[dataset.gt_poses[i] for i, _, _ in kept],
        timestamps=np.array([t for _, t, _ in kept], dtype=np.float64),
    )
    return kept, gt


def aligned(poses: Poses, gt: PoseTrajectory3D) -> PoseTrajectory3D:
    """``poses`` Sim(3)-aligned to ``gt`` (evo's Umeyama); raises evo's GeometryException when degenerate."""
    trajectory = _trajectory(poses)
    trajectory.align(gt, correct_scale=True)
    return trajectory


def _shown(poses: Poses, gt: PoseTrajectory3D | None) -> PoseTrajectory3D:
    if gt is not None:
        with contextlib.suppress(GeometryException):  # degenerate (no motion): shown unaligned
            return aligned(poses, gt)
    return _trajectory(poses)


def _save(figure: Any, folder: RunFolder, name: str) -> None:
    """Render ``figure`` as PNG in memory, then write it atomically (never through a symlink)."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    _pyplot()[0].close(figure)
    folder.write_bytes(name, buffer.getvalue())


def write_plots(
    folder: RunFolder,
    dataset: Dataset,
    odometry: Poses,
    final: Poses,
    loops: Sequence[LoopRecord],
    keyframe_frames: Mapping[int, int],
) -> list[str]:
    """Write the plots; returns the file names written."""
    if len(final) < 3:
        return []
    written = []
    odometry_kept, gt = with_ground_truth(dataset, odometry)
    final_kept, _ = with_ground_truth(dataset, final)
    if gt is None:
        odometry_kept, final_kept = odometry, final
    before, after = _shown(odometry_kept, gt), _shown(final_kept, gt)
    reference = gt.positions_xyz if gt is not None else after.positions_xyz
    axes = tuple(int(a) for a in np.sort(np.argsort(np.ptp(reference, axis=0))[-2:]))
    plt, evo_plot = _pyplot()
    mode = getattr(evo_plot.PlotMode, _MODES[(axes[0], axes[1])])
    figure = plt.figure(figsize=(8, 8))
    ax = evo_plot.prepare_axis(figure, mode)
    if gt is not None:
        evo_plot.traj(ax, mode, gt, style="-", color="black", label="ground truth")
    evo_plot.traj(ax, mode, before, style="-", color="tab:orange", label="odometry")
    evo_plot.traj(ax, mode, after, style="-", color="tab:blue", label="loop closed")
    position = {frame: n for n, (frame, _, _) in enumerate(final_kept)}
    accepted = [r for r in loops if r.accepted and r.query_frame in position and r.match_frame in position]
    for n, loop in enumerate(accepted):
        ends = after.positions_xyz[[position[loop.match_frame], position[loop.query_frame]]][:, list(axes)]
        ax.plot(*ends.T, color="tab:green", lw=0.8, alpha=0.8, label="accepted loops" if n == 0 else None)
    ax.legend(loc="best")
    name = display_path(dataset.root.name)
    ax.set_title(f"{name}: {len(accepted)} accepted loops ({len(keyframe_frames)} keyframes)")
    _save(figure, folder, TOP_VIEW_FILE)
    written.append(TOP_VIEW_FILE)
    if gt is not None:
        figure, ax = plt.subplots(figsize=(9, 4))
        for trajectory, color, label in (
            (before, "tab:orange", "odometry"),
            (after, "tab:blue", "loop closed"),
        ):
            ape = metrics.APE(metrics.PoseRelation.translation_part)
            ape.process_data((gt, trajectory))
            ax.plot(trajectory.timestamps - trajectory.timestamps[0], ape.error, color=color, label=label)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("APE translation (m, Sim(3)-aligned)")
        ax.legend(loc="best")
        _save(figure, folder, APE_FILE)
        written.append(APE_FILE)
    return written


def write_report(
    folder: RunFolder,
    figures: Mapping[str, Any],
    config: Mapping[str, Any],
    images: Sequence[str],
    loops: Sequence[LoopRecord],
) -> None:
    rows = "".join(
        f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(_fmt(v))}</td></tr>" for k, v in figures.items()
    )
    pictures = "".join(f'<p><img src="{html.escape(name)}" style="max-width:100%"></p>' for name in images)
    loop_rows = "".join(
        "<tr>"
        + "".join(
            f"<td>{html.escape(_fmt(v))}</td>"
            for v in (
                r.query,
                r.match,
                r.query_frame,
                r.match_frame,
                r.score,
                r.verified,
                r.inliers,
                r.accepted,
                r.scale,
                r.reason,
            )
        )
        + "</tr>"
        for r in loops
    )
    header = "".join(
        f"<th>{h}</th>"
        for h in (
            "query",
            "match",
            "query frame",
            "match frame",
            "score",
            "verified",
            "inliers",
            "accepted",
            "scale",
            "reason",
        )
    )
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>symbio run: {html.escape(str(figures.get("dataset", "")))}</title>
<style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:2px 8px;text-align:left}}</style></head><body>
<h1>symbio run</h1>
<h2>Metrics</h2><table>{rows}</table>
<h2>Plots</h2>{pictures or "<p>(no plots: fewer than three posed frames)</p>"}
<h2>Loops ({len(loops)} verified candidates)</h2><table><tr>{header}</tr>{loop_rows}</table>
<h2>Configuration</h2><pre>{html.escape(json.dumps(config, indent=2, sort_keys=True, default=str))}</pre>
</body></html>
"""
    folder.write_text(REPORT_FILE, page)


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return "" if value is None else str(value)
