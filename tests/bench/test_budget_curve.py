"""``python -m experiments.budget_curve`` run as a user runs it at a tiny size: one run extended point by point,
scored points kept on a rerun; never timings."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from user_commands import run_module

TINY_RECIPE = ["--set", "network.conv_channels=[4, 4, 4]", "--set", "network.squeeze_channels=2",
               "--set", "network.hidden=[16, 16, 16]", "--set", "code.n_axes=42", "--set", "code.n_angles=12",
               "--set", "code.sigma_from_symmetries=false", "--set", "train.batch_size=8"]



@pytest.mark.slow
def test_budget_curve_extends_one_run_and_resumes_from_its_scored_points(tmp_path: Path) -> None:
    args = ["--config", "trainer/configs/quick.toml", *TINY_RECIPE, "--images", "10", "--obj-ids", "3", "6",
            "--work", str(tmp_path / "work"), "--out", str(tmp_path), "--name", "tiny"]

    def curve(*epochs: str) -> list[dict]:
        """The points of ``python -m experiments.budget_curve ... --epochs EPOCHS``, as its results file holds them."""
        run_module("experiments.budget_curve", *args, "--epochs", *epochs)
        return json.loads((tmp_path / "budget-tiny.json").read_text(encoding="utf-8"))["points"]

    first = curve("1", "2")
    assert [p["epochs"] for p in first] == [1, 2]
    # The second point continued the first run: twice the crops, more seconds.
    assert first[1]["crop_updates"] == 2 * first[0]["crop_updates"] > 0
    assert first[1]["training_s"] > first[0]["training_s"]
    for point in first:
        assert set(point["mssd_per_object"]) == {"3", "6"}
        assert 0.0 <= point["mssd"] <= 1.0
        assert point["mssd_without_ambiguity"] == point["mssd_per_object"]["6"]  # part 6 has no symmetry
    again = curve("1", "2", "3")
    assert again[:2] == first  # scored points are kept, not retrained
    assert again[2]["crop_updates"] == 3 * first[0]["crop_updates"]
    assert "cpu_flags" in json.loads((tmp_path / "budget-tiny.json").read_text(encoding="utf-8"))["machine"]
    table = (tmp_path / "budget-tiny.md").read_text(encoding="utf-8").splitlines()
    assert [line.split("|")[1].strip() for line in table if line.startswith("| ") and line[2].isdigit()] == \
        ["1", "2", "3"]
    assert curve("2") == [first[1]]  # a scored budget alone: no training

