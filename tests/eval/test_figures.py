"""The metric-sensitivity figure: curves behave as the metrics must, and a PNG is written."""

from __future__ import annotations

import numpy as np
from box_render import box_depth_renderer
from symmetry_cases import CASES

from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_runtime.geometry.symmetries import symmetry_transforms
from popcode_trainer.eval.pipeline.sensitivity import sensitivity_curves
from popcode_trainer.eval.reporting.figures import axis_activations, plot_code_comparison, plot_sensitivity

K = np.array([[600.0, 0.0, 80.0], [0.0, 600.0, 60.0], [0.0, 0.0, 1.0]])
HALF_MM = np.array([40.0, 25.0, 10.0])
PTS_MM = HALF_MM * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
T_MM = np.array([0.0, 0.0, 800.0])
DIAMETER_MM = 2 * float(np.linalg.norm(HALF_MM))


def test_curves_start_at_zero_and_grow(tmp_path):
    render = box_depth_renderer(HALF_MM, K, 160, 120)
    angles = np.linspace(0.0, 180.0, 13)
    curves = sensitivity_curves(PTS_MM, None, DIAMETER_MM, K, np.eye(3), T_MM, angles,
                                np.random.default_rng(0), render_depth=render)
    assert set(curves.errors) == {"MSSD", "MSPD", "ADD", "ADI", "VSD", "VSS"}
    for name, values in curves.errors.items():
        assert values.shape == angles.shape
        assert values[0] == 0.0, name
    assert curves.errors["MSSD"][6] > curves.errors["MSSD"][1] > 0.0
    assert np.all(curves.errors["ADI"] <= curves.errors["ADD"] + 1e-9)
    assert np.all(curves.errors["VSS"] <= curves.errors["VSD"])
    path = plot_sensitivity(curves, tmp_path / "sensitivity.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_without_a_renderer_the_depth_metrics_are_left_out():
    syms = symmetry_transforms(CASES["two_fold"])
    curves = sensitivity_curves(PTS_MM, syms, DIAMETER_MM, K, np.eye(3), T_MM, np.array([0.0, 90.0]),
                                np.random.default_rng(1))
    assert set(curves.errors) == {"MSSD", "MSPD", "ADD", "ADI"}


def test_code_comparison_figure_full_and_axis_only(tmp_path):
    full = CodeLayout(n_axes=42, n_angles=12, sigma_deg=30.0)
    axis_only = CodeLayout(n_axes=42, sigma_deg=30.0, axis_only=True, symmetry_axis=(0.0, 0.0, 1.0))
    R = axis_angle_to_matrix(np.array([0.0, 0.6, 0.8]), 1.0)
    for layout in (full, axis_only):
        target = PopulationCode(layout).encode(R)
        predicted = 0.7 * target + np.random.default_rng(0).normal(0.0, 0.02, target.shape)
        activations = axis_activations(layout, target)
        assert activations.shape == (42,)
        assert np.argmax(activations) == PopulationCode(layout).decode(target).neuron[0] // (
            1 if layout.axis_only else layout.n_angles)
        path = plot_code_comparison(layout, predicted, target, tmp_path / f"code_{layout.axis_only}.png", "test")
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
