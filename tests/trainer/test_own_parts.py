"""The README's "Training on your own CAD models", as written, on two parts made here.

The commands are read from the README's section (its ```bash blocks) and run in-process with the
README's paths pointed at a temporary folder; only the sizes shrink (a hidden demo size, fewer images,
--set for epochs), so the test runs in seconds. Bad models folders are refused before anything is written.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from readme_text import README, bash_commands

from popcode_runtime import PoseEstimator
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.commands.cli import main as runtime_main
from popcode_trainer.cli import main
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.objects import BUILTIN_PARTS, model_info
from popcode_trainer.demo.files import SUMMARY_FILE
from popcode_trainer.demo.group_codes import choose_group_code, choose_group_codes, finer_grids
from popcode_trainer.demo.parts import check_models_folder
from popcode_trainer.demo.report import POPCODE
from popcode_trainer.demo.sizes import DEMO_SIZES
from popcode_trainer.demo.steps import small_config
from popcode_trainer.train.config import load_config

ROOT = Path(__file__).resolve().parents[2]
QUICK = ROOT / "trainer" / "configs" / "quick.toml"
SECTION = re.search(r"### Training on your own CAD models\n(.*?)\n### ", README, flags=re.DOTALL).group(1)
COMMANDS = bash_commands(SECTION)
Z_AXIS = {"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}
# What each command gets beyond the README's words: sizes a test affords.
SHRINK = {"demo": ["--size", "smoke"], "render": ["--quiet"], "preview": ["--count", "4"],
          "train": ["--set", "train.epochs=2", "--set", "train.batch_size=4", "--set", "data.val_fraction=0.25"]}
IMAGES = "12"  # instead of the README's 2000 per part


def _t_bracket() -> trimesh.Trimesh:
    """A part without symmetry: a T of two bars and a peg on one arm (mm), centred on its box: it reaches 0.65 of
    its diameter from its origin, so the demo frames it a little further away."""
    bar = trimesh.creation.box((80.0, 16.0, 12.0))
    stem = trimesh.creation.box((16.0, 50.0, 12.0))
    stem.apply_translation((0.0, -33.0, 0.0))
    peg = trimesh.creation.cylinder(radius=5.0, height=18.0)
    peg.apply_translation((28.0, 0.0, 15.0))
    mesh = trimesh.util.concatenate([bar, stem, peg])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def _flanged_pin() -> trimesh.Trimesh:
    """A part with a continuous symmetry about z and no flip: a pin with a flange at one end (mm)."""
    pin = trimesh.creation.cylinder(radius=8.0, height=40.0, sections=64)
    flange = trimesh.creation.cylinder(radius=18.0, height=6.0, sections=64)
    flange.apply_translation((0.0, 0.0, -17.0))
    mesh = trimesh.util.concatenate([pin, flange])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def _write_models(folder: Path, meshes: dict[int, tuple[trimesh.Trimesh, dict]]) -> Path:
    folder.mkdir(parents=True)
    for obj_id, (mesh, _) in meshes.items():
        mesh.export(folder / f"obj_{obj_id:06d}.ply")
    info = {str(obj_id): model_info(mesh, symmetries) for obj_id, (mesh, symmetries) in meshes.items()}
    (folder / "models_info.json").write_text(json.dumps(info))
    return folder


def _own_parts(folder: Path) -> Path:
    return _write_models(folder, {1: (_t_bracket(), {}), 2: (_flanged_pin(), {"symmetries_continuous": [Z_AXIS]})})


def _commands(program: str, subcommand: str) -> list[list[str]]:
    return [words for words in COMMANDS if words[:2] == [program, subcommand]]


def _pointed(words: list[str], paths: dict[str, Path]) -> list[str]:
    """The README's words with its example paths replaced by the test's (inside --set values too), in one pass."""
    pattern = re.compile("|".join(re.escape(name) for name in sorted(paths, key=len, reverse=True)))
    return [pattern.sub(lambda match: str(paths[match.group(0)]), word) for word in words]


def test_the_section_has_the_one_command_first_then_the_steps() -> None:
    order = [words[1] for words in COMMANDS]
    assert order == ["demo", "kit", "demo", "render", "preview", "train", "export", "predict"]
    assert "--check" in COMMANDS[2] and "--check" not in COMMANDS[0]
    assert "rgb/" not in SECTION and "about a minute per part" not in SECTION


def test_quick_config_is_the_demo_recipe() -> None:
    quick = load_config(QUICK)
    demo = DEMO_SIZES["quick"].pipeline.config
    paths = {"splits", "models_dir", "obj_ids"}
    assert {k: v for k, v in quick.to_dict()["data"].items() if k not in paths} == \
        {k: v for k, v in demo.to_dict()["data"].items() if k not in paths}
    assert quick.to_dict()["code"] == demo.to_dict()["code"]
    assert quick.to_dict()["network"] == demo.to_dict()["network"]
    train = {k: v for k, v in quick.to_dict()["train"].items() if k != "out_dir"}
    assert train == {k: v for k, v in demo.to_dict()["train"].items() if k != "out_dir"}


@pytest.mark.slow
def test_one_command(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The section's first command, at the hidden smoke size: render (clean, cluttered and training scenes), one
    model per symmetry group, export, both test splits, latency, and a report that names the parts."""
    models = _own_parts(tmp_path / "models")
    (words,) = [w for w in _commands("popcode-train", "demo") if "--check" not in w]
    out = tmp_path / "runs" / "mine"
    assert main(_pointed(words, {"path/to/models": models, "runs/mine": out})[1:] + SHRINK["demo"]) == 0
    summary = json.loads((out / SUMMARY_FILE).read_text())
    assert summary["object_groups"] == [[2], [1]]  # the continuous part apart from the other
    assert [sorted(PoseEstimator(p).metadata.objects) for p in summary["models"][POPCODE]] == [[2], [1]]
    assert PoseEstimator(summary["models"][POPCODE][0]).metadata.code.axis_only
    assert set(summary["cluttered_scores"]) >= {POPCODE, "single_variable"}
    report, card = (out / "report.md").read_text(), (out / "model_card.md").read_text()
    for text in (report, card):
        assert f"the 2 parts of `{models}` (objects 1, 2)" in text and "six built-in" not in text
        assert "- object 2: axis-only code, 42 axes, sigma 30 deg (the size's settings" in text
        assert "- object 1: full code 42 x 12" in text
        assert "Object 1 reaches 0.65 of its diameter from its origin" in text  # rendered further away
    assert "Every model started from random weights: no pretrained start is shipped for this network shape" in report
    assert set(summary["first_weights"]) == {"population_code_1", "population_code_2", "single_variable_1",
                                             "single_variable_2"}
    assert f"popcode-train demo --size smoke --objects {models} --out DIR" in card
    lines = [line.split() for line in report.splitlines() if line.startswith("popcode predict ")]
    assert runtime_main([str(out / w) if (out / w).is_file() else w for w in lines[0][1:]]) == 0
    assert "hypothesis 0" in capsys.readouterr().out


@pytest.mark.slow
def test_step_by_step(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The section's step-by-step commands; the predict command's image path is the render's, its box the one
    scene_gt_info.json gives."""
    models = _own_parts(tmp_path / "models")
    paths = {"path/to/models": models, "data/mine": tmp_path / "data" / "mine", "runs/mine": tmp_path / "runs" / "mine",
             "crops.png": tmp_path / "crops.png", "mine.onnx": tmp_path / "mine.onnx"}
    (check,) = [w for w in _commands("popcode-train", "demo") if "--check" in w]
    capsys.readouterr()
    assert main(_pointed(check, paths)[1:]) == 0
    groups = capsys.readouterr().out
    assert "- object 2: axis-only code, 642 axes" in groups and "- object 1: full code 642 x 36" in groups

    (render,) = _commands("popcode-train", "render")
    render = _pointed(render, paths)
    render[render.index("--images") + 1] = IMAGES
    assert main(render[1:] + SHRINK["render"]) == 0
    for step in ("preview", "train", "export"):
        (words,) = _commands("popcode-train", step)
        assert main(_pointed(words, paths)[1:] + SHRINK.get(step, [])) == 0, step
    assert (tmp_path / "crops.png").stat().st_size > 0

    (predict,) = _commands("popcode", "predict")
    predict = _pointed(predict, paths)
    image = Path(predict[3])
    assert image.is_file(), f"the README's image {image} is not where the render writes it"
    first = read_bop_split(paths["data/mine"], models).instances[0]
    assert first.image_path == image and first.obj_id == 1
    info = json.loads((image.parents[1] / "scene_gt_info.json").read_text())["0"][0]
    predict[predict.index("--box") + 1] = ",".join(str(v) for v in info["bbox_obj"])
    K = json.loads((image.parents[1] / "scene_camera.json").read_text())["0"]["cam_K"]
    assert predict[predict.index("--K") + 1] == f"{K[0]:g},{K[4]:g},{K[2]:g},{K[5]:g}", "README's K: not the render's"
    capsys.readouterr()
    assert runtime_main(predict[1:] + ["--json"]) == 0
    (prediction,) = json.loads(capsys.readouterr().out)["predictions"]
    assert prediction["obj_id"] == 1
    R = np.asarray(prediction["R_m2c"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)


def _metres() -> dict:
    mesh = _flanged_pin()
    mesh.apply_scale(0.001)
    return {1: (mesh, {})}


def _needle() -> dict:
    return {4: (trimesh.creation.cylinder(radius=1.0, height=100.0, sections=16), {"symmetries_continuous": [Z_AXIS]})}


def _wrongly_symmetric() -> dict:
    half_turn_about_z = np.diag([-1.0, -1.0, 1.0, 1.0]).ravel().tolist()  # the T is no 2-fold part
    return {3: (_t_bracket(), {"symmetries_discrete": [half_turn_about_z]})}


@pytest.mark.parametrize("make, expected", [
    (_metres, "object 1 (MODELS/obj_000001.ply): the mesh is 0.0"),
    (_needle, "object 4 (MODELS/obj_000004.ply): too thin to see"),
    (_wrongly_symmetric, "object 3 (MODELS/obj_000003.ply): symmetries_discrete[0] (rotation 180.0 deg"),
], ids=["metres", "too thin", "wrong symmetry"])
def test_bad_parts_stop_before_anything_is_written(make, expected: str, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture) -> None:
    models = _write_models(tmp_path / "models", make())
    out = tmp_path / "out"
    assert main(["demo", "--objects", str(models), "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and expected.replace("MODELS", str(models)) in error, error
    assert not out.exists()


def test_bad_folders_are_refused_with_the_fix(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(PopcodeError, match="has no models_info.json: a BOP models folder lists"):
        check_models_folder(empty)
    models = _own_parts(tmp_path / "models")
    info = (models / "models_info.json").read_text()
    (models / "models_info.json").write_text(info[:-1] + ', "01": ' + json.dumps(json.loads(info)["1"]) + "}")
    with pytest.raises(PopcodeError, match=r"models_info.json: '1' and '01' both stand for id 1"):
        check_models_folder(models)
    (models / "models_info.json").write_text(info)
    (models / "obj_000002.ply").unlink()
    with pytest.raises(PopcodeError, match="object 2: no mesh .*obj_000002.ply"):
        check_models_folder(models)


def test_a_run_folder_keeps_its_models(tmp_path: Path) -> None:
    """The models are copied into each split; a rerun after the folder's meshes changed is refused, not mixed."""
    models = _own_parts(tmp_path / "models")
    parts = check_models_folder(models)
    copy = parts.write_models(tmp_path / "out" / "train" / "models")
    assert (copy / "obj_000002.ply").read_bytes() == (models / "obj_000002.ply").read_bytes()
    assert parts.write_models(copy) == copy  # the same models again: fine
    _flanged_pin().apply_scale(1.01).export(models / "obj_000002.ply")
    with pytest.raises(PopcodeError, match="was started with another mesh of object 2"):
        check_models_folder(models).write_models(copy)
    assert parts.fill_range()[0][1] < 0.75  # the T-bracket is framed further away


def test_finer_grids_double_the_angles_then_quadruple_the_axes() -> None:
    assert finer_grids(642, 36, axis_only=False) == [(642, 36), (642, 72), (2562, 72)]
    assert finer_grids(642, 36, axis_only=True) == [(642, 36), (2562, 36), (10242, 36), (40962, 36), (163842, 36)]


@pytest.mark.slow
def test_a_grid_too_coarse_for_a_part_is_refined_and_said() -> None:
    """On the smoke size's 42 x 12 grid a 4-fold part's peaks merge at every width the grid resolves: the demo
    chooses 162 x 24 for it (unless told to keep the grid, as the built-in demo does) and says why."""
    code = small_config(1, 42, 12, sigma_deg=30.0).code
    four_fold = {4: BUILTIN_PARTS[3].symmetries}
    chosen = choose_group_code(code, four_fold)
    assert (chosen.code.n_axes, chosen.code.n_angles) == (162, 24) and chosen.sigma_deg < 30.0
    assert chosen.note.startswith("object 4: full code 162 x 24 instead of the size's full code 42 x 12, sigma "
                                  "narrowed to ")
    assert "object 4's 4 symmetric poses merge" in chosen.note
    kept = choose_group_code(code, four_fold, finer=False)
    assert kept.code == code and "the grid is too coarse" in kept.note


@pytest.mark.slow
def test_a_part_that_needs_a_finer_code_trains_apart() -> None:
    """A 4-fold part needs 162 x 24 at sigma 15 on the smoke grid; pooled with it, the asymmetric bracket would
    train on that grid and width too. It keeps the size's code in a model of its own, and both notes say why; the
    built-in demo (finer=False) keeps its one group."""
    code = small_config(1, 42, 12, sigma_deg=30.0).code
    info = {part.obj_id: part.symmetries for part in BUILTIN_PARTS if part.obj_id in (4, 6)}
    fine, kept = choose_group_codes(code, info, [[4, 6]])
    assert fine.obj_ids == (4,) and (fine.code.n_axes, fine.code.n_angles) == (162, 24) and fine.sigma_deg < 30.0
    assert fine.note.endswith("; a model apart from object 6, whose code differs")
    assert kept.obj_ids == (6,) and kept.code == code and kept.sigma_deg == 30.0
    assert kept.note.endswith("; a model apart from object 4, whose code differs")
    pooled, = choose_group_codes(code, info, [[4, 6]], finer=False)
    assert pooled.obj_ids == (4, 6) and pooled.code.n_axes == 42
