"""Figures as PNG: metric sensitivity to rotation error (the paper's Fig. 4) and a
predicted beside a target population code (the paper's Figs. 1 and 5).

Only drawing: the curves and codes are computed by :mod:`popcode_trainer.eval.pipeline.sensitivity` and
:mod:`popcode_trainer.eval.pipeline.instance_code`.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.coding.population_code import CodeLayout, check_code

from ..pipeline.instance_code import InstanceCode
from ..pipeline.sensitivity import SensitivityCurves


def save_figure(figure: Figure, path: str | Path) -> Path:
    """Lay the figure out (unless it has its own layout engine), write it as a PNG at exactly ``path``, atomically,
    and return the path (matplotlib itself would add ``.png`` to a folder's name and write there)."""
    path = Path(path)
    if path.is_dir():
        raise PopcodeError(f"{path} is a folder; give the path of the PNG to write")
    if figure.get_layout_engine() is None:
        figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    png = io.BytesIO()
    figure.savefig(png, format="png")
    write_bytes_atomic(path, png.getvalue())
    return path


def plot_sensitivity(curves: SensitivityCurves, path: str | Path, title: str = "") -> Path:
    """Write the curves as a PNG at ``path`` and return the path."""
    # A bare Figure renders with the Agg canvas and leaves pyplot's global state alone.
    figure = Figure(figsize=(6.0, 4.0), dpi=150)
    axes = figure.subplots()
    for name, values in curves.errors.items():
        axes.plot(curves.angles_deg, values, label=name, linewidth=1.5)
    axes.set_xlabel("rotation error [deg]")
    axes.set_ylabel("error (normalised)")
    axis = ", ".join(f"{v:.2f}" for v in curves.axis)
    axes.set_title(title or f"Metric sensitivity, rotation about ({axis})", fontsize=10)
    axes.set_xlim(curves.angles_deg.min(), curves.angles_deg.max())
    axes.set_ylim(bottom=0.0)
    axes.grid(alpha=0.3)
    axes.legend(fontsize=8)
    return save_figure(figure, path)


def axis_activations(layout: CodeLayout, code: np.ndarray) -> np.ndarray:
    """Activation ``(n_axes,)`` of each preferred axis: the maximum over its angles (the code itself if axis-only)."""
    code = check_code(code, layout.size)[0]
    return code if layout.axis_only else code.reshape(layout.n_axes, layout.n_angles).max(axis=1)


def sphere_panel(figure: Figure, position: int | tuple[int, int, int], layout: CodeLayout, activations: np.ndarray,
                 title: str, vmax: float, colorbar: bool = True, fontsize: float = 9) -> Axes:
    """Preferred axes on a Mollweide map (longitude = azimuth, latitude = elevation), coloured by activation.

    ``position`` is a subplot position (``131`` or ``(rows, columns, index)``); the one drawing of a
    code on the sphere, shared by the code figures and ``popcode-train preview``.
    """
    position = position if isinstance(position, tuple) else (position,)
    axes = figure.add_subplot(*position, projection="mollweide")
    x, y, z = layout.axes.T
    order = np.argsort(activations)  # strongest drawn last, on top
    points = axes.scatter(np.arctan2(y, x)[order], np.arcsin(np.clip(z, -1.0, 1.0))[order], c=activations[order],
                          s=max(2.0, 4000.0 / layout.n_axes), cmap="viridis", vmin=0.0, vmax=vmax)
    axes.set_xticklabels([])
    axes.grid(alpha=0.3)
    axes.set_title(title, fontsize=fontsize, pad=14)
    if colorbar:
        figure.colorbar(points, ax=axes, orientation="horizontal", fraction=0.05, pad=0.05)
    return axes


def plot_code_comparison(layout: CodeLayout, predicted: np.ndarray, target: np.ndarray, path: str | Path,
                         title: str = "") -> Path:
    """Predicted and target code of one crop side by side on the sphere of preferred axes; returns ``path``.

    A full code also gets its angle profile (activation over the preferred
    angles) at the axis where the target peaks.
    """
    predicted_axes, target_axes = axis_activations(layout, predicted), axis_activations(layout, target)
    vmax = float(max(predicted_axes.max(), target_axes.max(), 1e-6))
    columns = 2 if layout.axis_only else 3
    figure = Figure(figsize=(4.0 * columns, 3.4), dpi=150)
    over_angles = "" if layout.axis_only else " (max over angles)"
    sphere_panel(figure, 100 + 10 * columns + 1, layout, predicted_axes, f"predicted{over_angles}", vmax)
    sphere_panel(figure, 100 + 10 * columns + 2, layout, target_axes, f"target{over_angles}", vmax)
    if not layout.axis_only:
        peak = int(np.argmax(target_axes))
        profile = figure.add_subplot(133)
        angles_deg = np.degrees(layout.angles_rad)
        for name, code in (("predicted", predicted), ("target", target)):
            values = check_code(code, layout.size)[0].reshape(layout.n_axes, layout.n_angles)[peak]
            profile.plot(angles_deg, values, marker=".", label=name)
        profile.set_xlabel("preferred angle [deg]")
        profile.set_ylabel("activation")
        profile.set_title(f"angles at the target's peak axis {peak}", fontsize=9)
        profile.legend(fontsize=8)
        profile.grid(alpha=0.3)
    if title:
        figure.suptitle(title, fontsize=10)
    return save_figure(figure, path)


def plot_instance_code(code: InstanceCode, path: str | Path) -> Path:
    """An instance's predicted code beside its target (:func:`popcode_trainer.eval.pipeline.instance_code`)."""
    return plot_code_comparison(code.layout, code.predicted, code.target, path, code.title)
