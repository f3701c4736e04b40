"""The toy orientation task of the paper's Table I: ``python -m bench.toy_orientation --quick`` run as a user runs
it (every row of the table; never timings), and the shapes and symmetries its images are made of."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from user_commands import run_module

from tools.toy_task import BORDER, IMAGE_SIZE, PAPER, PERIOD_DEG, shape_polygons, square_symmetry


@pytest.mark.slow
def test_toy_orientation_has_every_row_of_table_one(tmp_path: Path) -> None:
    run_module("bench.toy_orientation", "--quick", "--jobs", "2", "--out", tmp_path)  # also the process pool
    payload = json.loads((tmp_path / "toy_orientation.json").read_text(encoding="utf-8"))
    records = payload["records"]
    for record in records:
        assert {"dataset", "method", "mean", "std", "runs"} <= set(record)
        assert record["runs"] == 1
    rows = {(r["dataset"], r["method"]) for r in records}
    assert set(PAPER) <= rows  # every row the paper reports
    assert {("arrows", "Population Code refined"), ("bars", "Population Code (Sym) refined")} <= rows
    assert ("arrows", "Population Code (Sym)") not in rows  # the paper's N/A
    table = (tmp_path / "toy_orientation.md").read_text(encoding="utf-8")
    for method in {m for _, m in rows}:
        assert f"| {method} |" in table


def test_toy_shapes_lie_inside_the_image_pointing_at_their_angle() -> None:
    # An arrow whose head leaves the image is a bar: no network can tell its direction.
    rng = np.random.default_rng(0)
    size, border = IMAGE_SIZE, BORDER
    for kind in PERIOD_DEG:
        for angle in rng.uniform(0.0, 2.0 * np.pi, size=300):
            polygons = shape_polygons(kind, angle, rng)
            points = np.concatenate(polygons)
            assert points.min() >= border and points.max() <= size - border
            if kind == "arrows":  # the head's tip lies along the angle (y up) from the shaft's centre
                direction = polygons[1][0] - polygons[0].mean(axis=0)
                assert np.isclose(np.arctan2(-direction[1], direction[0]) % (2 * np.pi), angle, atol=1e-9)


def test_square_symmetries_move_the_angle_with_the_image() -> None:
    # One lit pixel: its direction from the image centre (y up) is its angle, before and after every symmetry.
    size = IMAGE_SIZE
    image = np.zeros((1, 1, size, size), np.float32)
    image[0, 0, 10, 50] = 1.0

    def pixel_angle(picture: np.ndarray) -> float:
        row, column = np.argwhere(picture[0, 0])[0]
        centre = (size - 1) / 2.0
        return float(np.arctan2(centre - row, column - centre) % (2 * np.pi))

    angle, seen = np.array([pixel_angle(image)]), set()
    for quarter_turns in range(4):
        for mirror in (False, True):
            moved, angles = square_symmetry(image, angle, quarter_turns, mirror)
            assert moved.flags.c_contiguous and moved.shape == image.shape
            assert np.isclose(np.angle(np.exp(1j * (pixel_angle(moved) - angles[0]))), 0.0, atol=1e-12)
            seen.add(round(float(angles[0]), 9))
    assert len(seen) == 8  # eight different views
