"""Figures that summarise a run at a glance: training curves and test crops with their estimated poses."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from popcode_runtime.geometry.crop import crop_square, read_image, to_grey
from popcode_runtime.geometry.rotations import geodesic_angle
from popcode_runtime.geometry.symmetries import symmetry_transforms

from ...train.run_files import METRICS_FILE, read_metrics
from ..pipeline.evaluate import MethodResult
from .figures import save_figure

AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")  # object x, y, z


def plot_training_curves(metrics_files: Mapping[str, str | Path], path: str | Path) -> Path:
    """Training loss and validation error (up to symmetry) per epoch, one line per run; returns ``path``.

    Losses of different representations are not comparable, so each run's loss
    is divided by its first epoch's value.
    """
    figure = Figure(figsize=(10.0, 3.6), dpi=150)
    loss_axes, error_axes = figure.subplots(1, 2)
    for name, metrics_path in metrics_files.items():
        metrics = read_metrics(metrics_path, ("epoch", "train_loss", "val_error_median_deg"))
        loss_axes.plot(metrics["epoch"], metrics["train_loss"] / metrics["train_loss"][0], marker=".", label=name)
        error_axes.plot(metrics["epoch"], metrics["val_error_median_deg"], marker=".", label=name)
    loss_axes.set_ylabel("training loss / first epoch's")
    loss_axes.set_yscale("log")
    error_axes.set_ylabel("validation error, median [deg]")
    for axes in (loss_axes, error_axes):
        axes.set_xlabel("epoch")
        axes.grid(alpha=0.3)
        axes.legend(fontsize=7)
    return save_figure(figure, path)


def nearest_equivalent(R_true: np.ndarray, R_est: np.ndarray, info: Mapping) -> np.ndarray:
    """The ground-truth pose's symmetric equivalent closest to the estimate (the one worth drawing beside it)."""
    candidates = R_true @ symmetry_transforms(info).R
    return candidates[int(np.argmin(geodesic_angle(candidates, R_est)))]


def _draw_axes(axes, R: np.ndarray, centre: float, length: float, style: str, width: float) -> None:
    """The object's x, y, z axes seen by the camera (x right, y down), from the crop centre."""
    for k, colour in enumerate(AXIS_COLOURS):
        direction = R[:2, k]
        axes.plot([centre, centre + length * direction[0]], [centre, centre + length * direction[1]], style,
                  color=colour, linewidth=width)


def plot_crop_grid(result: MethodResult, path: str | Path, per_object: int = 2, columns: int = 6) -> Path:
    """Test crops with the estimated (solid) and true (dashed) object axes; returns ``path``.

    The true pose drawn is the symmetric equivalent nearest to the estimate, so
    a symmetric object estimated at another equivalent pose shows as correct.
    Each title gives the rotation error up to symmetry.
    """
    instances = result.split.instances
    chosen: list[int] = []
    for obj_id in result.split.obj_ids:
        chosen += [i for i, inst in enumerate(instances) if inst.obj_id == obj_id][:per_object]
    rows = -(-len(chosen) // columns)
    figure = Figure(figsize=(1.9 * columns, 2.1 * rows), dpi=120, layout="constrained")
    for slot, index in enumerate(chosen):
        inst = instances[index]
        crop = crop_square(to_grey(read_image(inst.image_path)), inst.box)
        R_est = result.R_est[index]
        R_true = nearest_equivalent(inst.R_m2c, R_est, result.split.models_info[inst.obj_id])
        error_deg = float(np.degrees(geodesic_angle(R_true, R_est)))
        axes = figure.add_subplot(rows, columns, slot + 1)
        axes.imshow(crop, cmap="gray", vmin=0.0, vmax=1.0)
        centre, length = crop.shape[0] / 2, crop.shape[0] * 0.35
        _draw_axes(axes, R_true, centre, length, "--", 1.2)
        _draw_axes(axes, R_est, centre, length, "-", 2.0)
        axes.set_title(f"obj {inst.obj_id}: {error_deg:.0f}°", fontsize=8)
        axes.set_axis_off()
    figure.suptitle(f"{result.name}: estimated (solid) and true (dashed) axes x/y/z = red/green/blue", fontsize=9)
    return save_figure(figure, path)


def metrics_files_of(run_dirs: Sequence[Path]) -> dict[str, Path]:
    """Run name -> its metrics file, for the runs that have one."""
    return {folder.name: folder / METRICS_FILE for folder in run_dirs if (folder / METRICS_FILE).is_file()}
