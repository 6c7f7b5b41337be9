"""Figures of evaluations (``relpoint evaluate --plot``) and comparisons (``relpoint compare --plot``).

Headless (matplotlib's Agg backend, imported on first use), written atomically as PNG, PDF or SVG
with a creator field naming relpoint (how :func:`formats.outputs.written_by_relpoint` knows them).

* Trajectory views: the aligned estimate, a thin line coloured by its APE translation error, over the
  reference drawn beneath it as a wide translucent band in a colour outside the error colour map (so
  the reference shows on both sides of the estimate where they coincide, at any scale); the run's
  landmarks with the dynamic ones marked, and the true landmarks when known; the title names the run,
  the estimator and the alignment.
* Errors over time: APE and RPE translation and rotation.
* Comparison: box or violin plots of each run's APE and RPE translation errors, and the APE
  translation of every run over time, in one figure.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import relpoint
from formats.atomic import atomic_path
from relpoint.evaluation import AlignMode, EvaluationResult
from relpoint.evaluation.comparison import SERIES, ComparedRun
from relpoint.types import GroundTruthLandmarks, LandmarkMap, Trajectory

PLOT_FORMATS = ("png", "pdf", "svg")

#: The evaluation figures, by stem; ``relpoint evaluate --plot DIR`` writes ``STEM.FORMAT`` for each.
EVALUATION_PLOTS = ("trajectory_top", "trajectory_side", "errors")

#: How a title names each alignment.
ALIGN_NAMES = {
    AlignMode.NONE: "not aligned",
    AlignMode.SE3: "SE(3) Umeyama alignment",
    AlignMode.SIM3: "Sim(3) Umeyama alignment",
    AlignMode.SCALE: "scale corrected",
    AlignMode.ORIGIN: "origin alignment",
}

_ERROR_CMAP = "plasma"  # dark blue to yellow: no green, so the reference's colour stands apart
_REFERENCE_COLOUR = "#1a9e3f"
_DYNAMIC_COLOUR = "#d62728"


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    return plt


def save_figure(fig: Any, path: Path, plot_format: str = "png") -> Path:
    """Save ``fig`` to ``path`` atomically in ``plot_format`` and close it; returns ``path``."""
    plt = _pyplot()
    creator = f"relpoint {relpoint.__version__}"
    metadata = {"Software": creator} if plot_format == "png" else {"Creator": creator}
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=plot_format, dpi=110, bbox_inches="tight", metadata=metadata)
    finally:
        plt.close(fig)
    return path


def plot_title(run: str, estimator: str, align: AlignMode | str) -> str:
    """``RUN - ESTIMATOR - ALIGNMENT`` (the parts that are known)."""
    mode = AlignMode.parse(align) if align else None
    parts = [run, estimator or "", ALIGN_NAMES[mode] if mode is not None else ""]
    return " - ".join(part for part in parts if part)


def _coloured_path(ax: Any, xy: np.ndarray, errors: np.ndarray, norm: Any) -> Any:
    """The path as segments coloured by the mean error of their two ends; returns the collection."""
    from matplotlib.collections import LineCollection

    segments = np.stack((xy[:-1], xy[1:]), axis=1)
    values = 0.5 * (errors[:-1] + errors[1:]) if len(errors) > 1 else errors
    lines = LineCollection(segments, cmap=_ERROR_CMAP, norm=norm, linewidths=1.3, zorder=2)
    lines.set_array(values)
    ax.add_collection(lines)
    return lines


def _draw_landmarks(
    ax: Any, axes: tuple[int, int], landmarks: LandmarkMap | None, truth: GroundTruthLandmarks | None,
    alignment: Any,
) -> None:  # fmt: skip
    a, b = axes
    if truth is not None and len(truth.ids):
        static = ~truth.dynamic
        ax.scatter(truth.positions[static, a], truth.positions[static, b], s=14, facecolors="none",
                   edgecolors="0.55", linewidths=0.6, zorder=1, label="true landmarks")  # fmt: skip
    if landmarks is None or not len(landmarks):
        return
    positions = alignment.apply_positions(landmarks.positions) if alignment is not None else landmarks.positions
    static = ~landmarks.dynamic
    ax.scatter(positions[static, a], positions[static, b], s=5, color="0.2", zorder=3,
               label=f"landmarks ({int(static.sum())})")  # fmt: skip
    if landmarks.dynamic.any():
        ax.scatter(positions[~static, a], positions[~static, b], s=28, marker="x", color=_DYNAMIC_COLOUR,
                   linewidths=1.2, zorder=4, label=f"dynamic landmarks ({int(landmarks.dynamic.sum())})")  # fmt: skip


def evaluation_plots(
    directory: Path,
    reference: Trajectory,
    result: EvaluationResult,
    *,
    run: str,
    estimator: str = "",
    landmarks: LandmarkMap | None = None,
    truth: GroundTruthLandmarks | None = None,
    plot_format: str = "png",
) -> list[Path]:
    """``trajectory_top`` (x-y), ``trajectory_side`` (x-z) and ``errors`` in ``directory``.

    ``reference`` is drawn whole, in its own frame; the estimate is the result's matched poses after
    the alignment, coloured by APE translation (m). ``landmarks`` (the run's map, estimate frame) are
    moved by the alignment when there is one; ``truth`` is drawn as is (reference frame).
    """
    from matplotlib.colors import Normalize

    plt = _pyplot()
    title = plot_title(run, estimator, result.settings.align)
    alignment = result.alignment if result.settings.align is not AlignMode.NONE else None
    est = result.matched.estimate_positions
    errors = result.ape_translation
    # From zero, so that a colour means the same error in every run's figure; a constant error gets its own colour.
    norm = Normalize(vmin=0.0, vmax=float(max(errors.max(), 1e-6)))
    written = []
    for stem, (a, b), view in (
        ("trajectory_top", (0, 1), "top view (x-y)"),
        ("trajectory_side", (0, 2), "side view (x-z)"),
    ):
        fig, ax = plt.subplots(figsize=(8, 6.5))
        ax.plot(reference.positions[:, a], reference.positions[:, b], color=_REFERENCE_COLOUR, lw=5.0,
                alpha=0.45, solid_capstyle="round", zorder=1.5, label="reference")  # fmt: skip
        lines = _coloured_path(ax, est[:, [a, b]], errors, norm)
        ax.plot([], [], color=plt.get_cmap(_ERROR_CMAP)(0.6), lw=1.3, label="estimate")  # legend entry
        _draw_landmarks(ax, (a, b), landmarks, truth, alignment)
        fig.colorbar(lines, ax=ax, label="APE translation (m)", shrink=0.85)
        ax.set_xlabel("xyz"[a] + " (m)")
        ax.set_ylabel("xyz"[b] + " (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
        ax.set_title(f"{title}\n{view}", fontsize=10)
        ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3)
        written.append(save_figure(fig, directory / f"{stem}.{plot_format}", plot_format))
    seconds = (result.stamps_ns - result.stamps_ns[0]) * 1e-9
    fig, (ax_t, ax_r) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    ax_t.plot(seconds, result.ape_translation, color="tab:red", lw=1.0, label="APE")
    ax_r.plot(seconds, result.ape_rotation_deg, color="tab:red", lw=1.0, label="APE")
    if result.rpe_translation is not None and result.rpe_rotation_deg is not None:
        second = result.rpe_translation.second
        ax_t.plot(seconds[second], result.rpe_translation.errors, color="tab:green", lw=0.8, label="RPE")
        ax_r.plot(seconds[second], result.rpe_rotation_deg.errors, color="tab:green", lw=0.8, label="RPE")
    ax_t.set_ylabel("translation error (m)")
    ax_r.set_ylabel("rotation error (deg)")
    ax_r.set_xlabel("time since first matched pose (s)")
    ax_t.set_title(title, fontsize=10)
    for ax in (ax_t, ax_r):
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left")
    written.append(save_figure(fig, directory / f"errors.{plot_format}", plot_format))
    return written


def _distribution(ax: Any, runs: Sequence[ComparedRun], key: str, kind: str) -> None:
    colour_of = dict(zip((run.label for run in runs), _run_colours(len(runs)), strict=True))
    with_series = [run for run in runs if key in run.series and len(run.series[key])]
    ax.set_title(SERIES[key][0], fontsize=10)
    ax.grid(alpha=0.3, axis="y")
    if not with_series:
        ax.text(0.5, 0.5, "no per-pose errors", ha="center", va="center", transform=ax.transAxes, color="0.4")
        return
    data = [run.series[key].errors[np.isfinite(run.series[key].errors)] for run in with_series]
    labels = [run.label for run in with_series]
    positions = np.arange(1, len(data) + 1)
    if kind == "violin":
        parts = ax.violinplot(data, positions=positions, showmedians=True, widths=0.8)
        parts["cmedians"].set_color("black")
        for name in ("cbars", "cmins", "cmaxes"):
            parts[name].set_color("0.35")
        for body, colour in zip(parts["bodies"], (colour_of[label] for label in labels), strict=True):
            body.set_facecolor(colour)
            body.set_alpha(0.6)
    else:
        boxes = ax.boxplot(data, positions=positions, widths=0.6, patch_artist=True, showfliers=True,
                           flierprops={"markersize": 2, "alpha": 0.5}, medianprops={"color": "black"})  # fmt: skip
        for box, colour in zip(boxes["boxes"], (colour_of[label] for label in labels), strict=True):
            box.set_facecolor(colour)
            box.set_alpha(0.6)
    ax.set_xticks(positions)
    ax.set_xticklabels(labels, rotation=20, ha="right", fontsize=8)


def _run_colours(n: int) -> list[Any]:
    plt = _pyplot()
    cmap = plt.get_cmap("tab10")
    return [cmap(i % 10) for i in range(n)]


def comparison_plot(path: Path, runs: Sequence[ComparedRun], *, kind: str = "box", plot_format: str = "png") -> Path:
    """One figure of every run: APE and RPE translation distributions (box or violin) above, APE
    translation over time below. Runs without a series are named in the panel and left out of it."""
    plt = _pyplot()
    fig = plt.figure(figsize=(11, 8.5))
    grid = fig.add_gridspec(2, 2, height_ratios=(1, 1.1), hspace=0.45, wspace=0.25)
    _distribution(fig.add_subplot(grid[0, 0]), runs, "ape_trans", kind)
    _distribution(fig.add_subplot(grid[0, 1]), runs, "rpe_trans", kind)
    ax = fig.add_subplot(grid[1, :])
    for run, colour in zip(runs, _run_colours(len(runs)), strict=True):
        series = run.series.get("ape_trans")
        if series is not None and len(series):
            ax.plot(series.seconds, series.errors, color=colour, lw=1.0, label=run.label)
    ax.set_xlabel("time since first matched pose (s)")
    ax.set_ylabel(SERIES["ape_trans"][0])
    ax.set_title("APE translation over time", fontsize=10)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", fontsize=8)
    aligns = sorted({run.align for run in runs if run.align})
    fig.suptitle(f"{len(runs)} runs compared" + (f" - {', '.join(ALIGN_NAMES[AlignMode.parse(a)] for a in aligns)}"
                                                  if aligns else ""))  # fmt: skip
    return save_figure(fig, path, plot_format)
