"""``popcode-train kit`` at the hidden smoke size on three built-in parts written out as a user's models folder: the
kit's layout, its models in the runtime, its card, a rerun that redoes nothing, and the refusals of a kit folder
that belongs to another kit or whose models folder changed (the budget's refusals: the hostile catalogue)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from hostile_cases import refused_in_one_line, run_cli

from popcode_runtime.inference.detector import Detector
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_trainer.cli import main
from popcode_trainer.data.objects import write_builtin_models
from popcode_trainer.demo.files import SUMMARY_FILE
from popcode_trainer.kit.budget import ANCHORS, MAX_HOURS, MIN_HOURS, WIDE_NETWORK, kit_size
from popcode_trainer.kit.layout import CARD_FILE, DETECTOR_NAME, SAMPLES_FOLDER
from popcode_trainer.kit.run import KIT_FILE, WORK_FOLDER, finished_demo
from tools.paths import ROOT

HOURS = "1"
PARTS = [1, 2, 6]  # two models: the two parts of a continuous symmetry together, the asymmetric bracket alone


def _kit(models: Path, out: Path, hours: str = HOURS) -> list[str]:
    return ["kit", "--objects", str(models), "--out", str(out), "--hours", hours, "--size", "smoke"]


@pytest.fixture(scope="module")
def kit(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The models folder and the finished kit."""
    folder = tmp_path_factory.mktemp("kit")
    models = _builtin_parts(folder / "models", PARTS)
    assert main(_kit(models, folder / "kit")) == 0
    return models, folder / "kit"


def _builtin_parts(folder: Path, obj_ids: list[int]) -> Path:
    """Those built-in parts alone as a user's models folder (fewer parts: a third less work than all six)."""
    write_builtin_models(folder)
    info = json.loads((folder / "models_info.json").read_text())
    for obj_id in [int(key) for key in info if int(key) not in obj_ids]:
        del info[str(obj_id)]
        (folder / f"obj_{obj_id:06d}.ply").unlink()
    (folder / "models_info.json").write_text(json.dumps(info))
    return folder


@pytest.mark.slow
def test_the_kit_is_laid_out_as_models_and_loads_in_the_runtime(kit: tuple[Path, Path]) -> None:
    _, out = kit
    record = json.loads((out / KIT_FILE).read_text())["kit"]
    pose_files = sorted(p.name for p in out.glob("parts-*.onnx") if p.name != DETECTOR_NAME)
    assert pose_files == sorted(Path(p).name for p in record["models"])
    assert {p.name for p in out.iterdir()} == {*pose_files, DETECTOR_NAME, SAMPLES_FOLDER, CARD_FILE, KIT_FILE,
                                               WORK_FOLDER}
    covered = [obj_id for name in pose_files for obj_id in PoseEstimator(out / name).metadata.objects]
    assert sorted(covered) == PARTS and len(pose_files) == 2  # every part in exactly one model
    assert all(name == f"parts-{'-'.join(map(str, sorted(PoseEstimator(out / name).metadata.objects)))}.onnx"
               for name in pose_files)
    assert sorted(Detector(out / DETECTOR_NAME).metadata.obj_ids) == PARTS
    samples = json.loads((out / SAMPLES_FOLDER / "samples.json").read_text())
    assert [s["obj_id"] for s in samples["samples"]] == PARTS
    assert samples["bin"]["instances"] and (out / SAMPLES_FOLDER / samples["bin"]["image"]).is_file()
    assert all((out / SAMPLES_FOLDER / s["image"]).is_file() for s in samples["samples"])


@pytest.mark.slow
def test_the_card_names_its_scores_machine_and_command(kit: tuple[Path, Path]) -> None:
    models, out = kit
    card = (out / CARD_FILE).read_text()
    assert f"Made by `popcode-train kit --objects {models} --out {out} --hours {HOURS} --size smoke`" in card
    for row in ("| clean (2 images a part), the shipped files | ", "| bin (2 scenes), true boxes, float copies | ",
                "| bin, from the frame: the kit's detector's boxes | "):
        assert row in card and card.split(row)[1].split(" |")[0].endswith("%"), row
    assert "The detector on the bin split (COCO AP" in card and " cores, load " in card
    assert "not measured yet" in card


@pytest.mark.slow
def test_a_rerun_of_a_finished_kit_redoes_nothing(kit: tuple[Path, Path], capsys: pytest.CaptureFixture) -> None:
    models, out = kit
    files = sorted(p for p in out.rglob("*") if p.is_file())
    before = {p: p.stat().st_mtime_ns for p in files}
    capsys.readouterr()
    assert main(_kit(models, out)) == 0
    assert f"{out} is complete" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in files} == before


@pytest.mark.slow
def test_another_kits_folder_is_refused_naming_what_differs(kit: tuple[Path, Path]) -> None:
    models, out = kit
    code, _, stderr = run_cli(_kit(models, out, hours="2"), main)
    assert refused_in_one_line(code, stderr, f"{out} holds a kit started with --hours 1, not 2: rerun that command")


@pytest.mark.slow
def test_a_changed_models_folder_is_refused_naming_the_file(kit: tuple[Path, Path], tmp_path: Path) -> None:
    models, out = kit
    changed = shutil.copytree(models, tmp_path / "models")
    started = tmp_path / "kit"
    started.mkdir()
    record = json.loads((out / KIT_FILE).read_text())
    (started / KIT_FILE).write_text(json.dumps({**record, "objects": str(changed.resolve())}))
    info = json.loads((changed / "models_info.json").read_text())
    info["6"]["diameter"] *= 1.001  # within the check's tolerance: the parts still pass, but they are not the same
    (changed / "models_info.json").write_text(json.dumps(info))
    code, _, stderr = run_cli(_kit(changed, started), main)
    assert refused_in_one_line(code, stderr, f"the models folder {changed.resolve()} changed since {started} was "
                                             "started (models_info.json)")


def test_the_budget_grows_the_data_between_the_anchors() -> None:
    sizes = [kit_size(h, path_tracing=True) for h in (MIN_HOURS, 0.5, ANCHORS[1].hours, 2.0, ANCHORS[-1].hours,
                                                      MAX_HOURS)]
    for field in ("train_images_per_object", "train_scenes", "cluttered_test_scenes", "detector_seconds"):
        values = [getattr(s, field) for s in sizes]
        assert values == sorted(values), field
    assert sizes[0].train_scenes == ANCHORS[0].train_scenes and sizes[-2].train_scenes == ANCHORS[-1].train_scenes
    assert sizes[-1].config.network == WIDE_NETWORK and sizes[2].config.network != WIDE_NETWORK
    assert sizes[-1].traced_train_images and not kit_size(MAX_HOURS, path_tracing=False).traced_train_images
    assert all(s.representations == ("population_code",) for s in sizes)


@pytest.mark.slow
def test_an_interrupted_kit_resumes_without_running_its_demo_again(kit: tuple[Path, Path], tmp_path: Path) -> None:
    """A copy of the kit as a run cut off after its demo finished leaves it (no card, no files laid out; the demo's
    summary names the copy's folder, as in the folder it ran in): the kit is laid out from the summary, with the
    same card, and nothing in the work folder is trained, evaluated or written again."""
    models, finished = kit
    out = shutil.copytree(finished, tmp_path / "kit")
    record = json.loads((out / KIT_FILE).read_text())
    del record["kit"]
    (out / KIT_FILE).write_text(json.dumps(record))
    for path in [out / CARD_FILE, *out.glob("parts-*.onnx")]:
        path.unlink()
    summary = out / WORK_FOLDER / SUMMARY_FILE
    summary.write_text(summary.read_text().replace(str(finished), str(out)))
    work = sorted(p for p in (out / WORK_FOLDER).rglob("*") if p.is_file())
    before = {p: p.stat().st_mtime_ns for p in work}
    assert main(_kit(models, out)) == 0
    assert {p: p.stat().st_mtime_ns for p in work} == before
    assert "kit" in json.loads((out / KIT_FILE).read_text())
    assert sorted(p.name for p in out.glob("parts-*.onnx")) == sorted(p.name for p in finished.glob("parts-*.onnx"))
    assert _without_load((out / CARD_FILE).read_text()) == _without_load(
        (finished / CARD_FILE).read_text().replace(str(finished), str(out)))


def _without_load(card: str) -> str:
    """The card but the machine's load when it was written."""
    return re.sub(r", load [0-9.]+,", ", load,", card)


def test_a_summary_the_kit_cannot_use_leaves_the_demo_to_run(tmp_path: Path) -> None:
    """No summary, one of another folder, one whose model is gone, one without the models: the demo runs (its
    steps resume); a summary of this folder whose files are there is used."""
    work = tmp_path / WORK_FOLDER
    work.mkdir()
    model, samples = work / "model.onnx", work / "samples.json"
    model.write_bytes(b"onnx")
    samples.write_text("{}")
    usable = {"report": str(work / "report.md"), "models": {"population_code": [str(model)]},
              "quantised_models": [], "samples": str(samples)}
    assert finished_demo(work) is None
    for summary in ({**usable, "report": str(tmp_path / "elsewhere" / "report.md")}, {**usable, "samples": None},
                    {key: value for key, value in usable.items() if key != "models"}, []):
        (work / SUMMARY_FILE).write_text(json.dumps(summary))
        assert finished_demo(work) is None, summary
    (work / SUMMARY_FILE).write_text(json.dumps(usable))
    assert finished_demo(work) == usable
    model.unlink()
    assert finished_demo(work) is None


def test_the_docs_table_of_the_budget_is_the_code_s() -> None:
    text = (ROOT / "docs" / "training.md").read_text()
    for anchor in ANCHORS:
        hours = f"{anchor.hours:g}" + (" and more" if anchor is ANCHORS[-1] else "")
        assert (f"| {hours} | {anchor.train_images} | {anchor.train_scenes} | {anchor.test_images} / "
                f"{anchor.cluttered_test_scenes} |") in text, hours
