"""Smoke tests of ``python -m bench.translation`` and ``python -m bench.agreement`` run as a user runs them at tiny
sizes: the JSON contract and the table rows; never timings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from onnx_models import linear_model, save
from user_commands import run_module

from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.geometry.rotations import random_rotations
from popcode_runtime.geometry.symmetries import symmetry_rotations
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.hull import HULL_POINTS
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split

HULL, CORNERS = f"{HULL_POINTS} hull points", "3-D box corners"  # the points bench.translation fits
TRANSLATION_ROWS = (f"{HULL}, rendered box", f"{CORNERS}, rendered box", f"{HULL}, exact box")


@pytest.mark.slow
def test_translation_compares_hull_points_with_box_corners(tmp_path: Path) -> None:
    run_module("bench.translation", "--quick", "--out", tmp_path)
    payload = json.loads((tmp_path / "translation-quick.json").read_text(encoding="utf-8"))
    assert {"cpu", "cores", "onnxruntime", "torch"} <= set(payload["machine"])
    rows = payload["translation"]
    assert list(rows) == list(TRANSLATION_ROWS) and payload["settings"]["instances"] == 18
    hull, corners, exact = (rows[row] for row in TRANSLATION_ROWS)
    assert hull["median_te_percent"] < corners["median_te_percent"]  # corners lie outside the silhouette
    assert exact["median_te_percent"] < hull["median_te_percent"]  # pixel rounding is the larger error
    assert sorted(payload["per_object"][TRANSLATION_ROWS[0]]) == ["1", "2", "3", "4", "5", "6"]
    assert list(payload["full_pose_groups"]) == [HULL, CORNERS]
    table = (tmp_path / "translation-quick.md").read_text(encoding="utf-8")
    assert all(f"| {row} |" in table for row in TRANSLATION_ROWS)


def test_agreement_counts_symmetric_swaps_as_the_same_pose_per_object(tmp_path: Path) -> None:
    # Constant-output models: the reference encodes R0, the other R0 S with S a symmetry of object 3 but
    # not of object 6, so crops of 3 agree on the pose (not the argmax) and crops of 6 agree on neither.
    split = render_builtin_split(tmp_path / "split", 2, obj_ids=[3, 6], random_position=True)
    models_info = load_models_info(split / BUILTIN_MODELS_FOLDER)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE, code=CodeLayout(n_axes=162, n_angles=12),
                             objects={3: models_info[3], 6: models_info[6]}, input_size=128)
    code = PopulationCode(metadata.code)
    R0 = random_rotations(1, np.random.default_rng(0))[0]
    S = symmetry_rotations(models_info[3])[1]
    reference = save(linear_model(code.encode(R0), metadata=metadata), tmp_path / "float.onnx")
    swapped = save(linear_model(code.encode(R0 @ S), metadata=metadata), tmp_path / "swapped.onnx")
    run_module("bench.agreement", reference, reference, swapped, "--split", split, "--out", tmp_path)
    records = json.loads((tmp_path / "agreement.json").read_text(encoding="utf-8"))["records"]
    by_row = {(r["model"], r["obj_id"]): r for r in records}
    assert {key[1] for key in by_row} == {"all", 3, 6} and by_row["float.onnx", "all"]["crops"] == 4
    assert all(by_row["float.onnx", obj][name] == 1.0 for obj in ("all", 3, 6)
               for name in ("argmax_agreement", "pose_agreement"))
    assert by_row["swapped.onnx", 3]["argmax_agreement"] == 0.0 and by_row["swapped.onnx", 3]["pose_agreement"] == 1.0
    assert by_row["swapped.onnx", 6]["pose_agreement"] == 0.0 and by_row["swapped.onnx", "all"]["pose_agreement"] == 0.5
    assert (tmp_path / "agreement.md").read_text(encoding="utf-8").count("| swapped.onnx |") == 3
