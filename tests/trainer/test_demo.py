"""The demo end to end at a tiny size: every file of the run folder, the report's links, resuming (its steps:
test_demo_steps.py)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tiny_demo import TINY

from popcode_runtime import PoseEstimator
from popcode_runtime.commands.cli import main as runtime_main
from popcode_trainer.demo import epoch_budget
from popcode_trainer.demo.files import SUMMARY_FILE
from popcode_trainer.demo.report import POPCODE
from popcode_trainer.demo.run import run_demo
from tools.paths import ROOT

BUDGET_MINUTES = 0.01  # less than the steps take: the epochs are fitted to the lowest bound, 2
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("demo")
    return out, run_demo("tiny", out, TINY, latency_iterations=3, minutes=BUDGET_MINUTES)


@pytest.mark.slow
def test_report_links_exist_and_tables_are_complete(demo_run: tuple[Path, dict]) -> None:
    out, summary = demo_run
    report = (out / "report.md").read_text()
    links = re.findall(r"\]\(([^)]+)\)", report)
    assert len(links) >= 10
    for link in links:
        assert (out / link).is_file(), link
    assert json.loads((out / SUMMARY_FILE).read_text())["report"] == str(out / "report.md")
    assert re.search(r"training step: (eager|compiled), (channels_last|NCHW), (fp32|bf16) \(", report)  # what ran
    methods = {"population_code", "population_code (refined)", "population_code (int8)", "single_variable"}
    assert set(summary["scores"]) == methods
    for name in methods:
        assert f"| {name} |" in report
        all_objects = summary["scores"][name]["All objects"]
        assert 0.0 <= all_objects["MSSD"] <= 1.0
    assert set(summary["confidence"]) == methods  # each judged: a calibrated confidence or its raw score
    assert "## Against the paper's accuracy" in report and "| MSSD over all parts |" in report
    for name in methods:
        assert 0.0 <= summary["confidence"][name]["mssd_at_coverage"]["0.5"] <= 1.0
    assert "### Confidence" in report
    # the 6-D section: the population code placed with depth and refined against it, beside the box
    assert "| population_code, depth |" in report and "| population_code, depth + ICP |" in report
    assert "## The robot's bin: clean and cluttered test splits" in report  # both methods on both splits
    assert "2 cluttered bin scenes of them that make 50 % of every epoch's crops" in report  # trained on scenes
    assert "trained population_code, single_variable on crops of true boxes with" in report  # tiny: true boxes
    assert set(summary["cluttered_scores"]) == {"population_code", "single_variable",
                                                "population_code, detector-like boxes", "own detector",
                                                "population_code, own detector"}
    own = summary["cluttered_scores"].pop("own detector")
    assert 0.0 <= own["detection"]["AP"] <= 1.0 and own["detection"]["detections"] <= 5 * 2
    assert "## The run's own eyes: a detector from the same renders" in report
    assert "| the run's own detector (every instance; a missed one is wrong) |" in report
    # the first test image of every part path traced: scored on both looks, the difference reported
    traced = summary["path_traced_scores"]
    assert traced["images"] == 6 and traced["rendered"].keys() == traced["path_traced"].keys()
    assert "## What to expect on a real camera: path-traced test images" in report and "| difference |" in report
    assert len(list((out / "test_path_traced").glob("*/gray/*.png"))) == 6
    assert all(0.0 <= s["groups"]["All objects"]["MSSD"] <= 1.0 for s in summary["cluttered_scores"].values())
    top_k = summary["cluttered_scores"]["population_code"]["best_of_top_k"]
    assert top_k[3]["All objects"] >= top_k[1]["All objects"]
    assert summary["cluttered_scores"]["single_variable"]["best_of_top_k"] is None
    assert "| best of top-2 | best of top-3 |" in report and "| population_code, detector-like boxes |" in report
    assert "| MSSD in the cluttered bin |" in report and "| lead over single_variable in the bin |" in report
    detector_target = next(line for line in report.splitlines() if line.startswith("| detector-like boxes"))
    # a missed detector target names the lever and what this run trained on
    assert ("missed" in detector_target) == ("this run trained on crops of true boxes." in report)
    # 3 models x 2 batches x 2 stages, each with a positive median
    assert len(summary["latency"]) == 12
    assert all(record["median_ms"] > 0 for record in summary["latency"])
    for paths in summary["figures"].values():
        for path in paths:
            assert Path(path).read_bytes()[:8] == PNG_SIGNATURE


@pytest.mark.slow
def test_report_commands_run_on_the_runtime(demo_run: tuple[Path, dict], capsys: pytest.CaptureFixture) -> None:
    """The report's `popcode` examples run as written, from the run folder."""
    out, _ = demo_run
    lines = [line.split() for line in (out / "report.md").read_text().splitlines() if line.startswith("popcode ")]
    assert [words[1] for words in lines] == ["info", "predict"]
    for words in lines:
        args = [str(out / word) if (out / word).is_file() else word for word in words[1:]]
        assert runtime_main(args) == 0, " ".join(words)
    assert "hypothesis 0" in capsys.readouterr().out


@pytest.mark.slow
def test_models_and_card(demo_run: tuple[Path, dict]) -> None:
    out, summary = demo_run
    popcode = [Path(p) for p in summary["models"][POPCODE]]
    assert [sorted(PoseEstimator(p).metadata.objects) for p in popcode] == [[1, 2], [3, 4, 5, 6]]
    for path in map(Path, summary["quantised_models"]):
        assert PoseEstimator(path).metadata.representation == POPCODE
    card = (out / "model_card.md").read_text()
    assert "objects 3 (2 symmetric poses), 4 (4 symmetric poses)" in card
    assert "popcode-train demo --size tiny" in card
    samples = json.loads(Path(summary["samples"]).read_text())["samples"]
    assert [s["obj_id"] for s in samples] == [1, 2, 3, 4, 5, 6]
    for sample in samples:
        assert (Path(summary["samples"]).parent / sample["image"]).is_file()
        assert np.allclose(np.linalg.det(np.array(sample["R_m2c"])), 1.0)


@pytest.mark.slow
def test_rerun_resumes_without_retraining(demo_run: tuple[Path, dict]) -> None:
    out, summary = demo_run
    model = Path(summary["models"][POPCODE][0])
    before = model.stat().st_mtime_ns
    again = run_demo("tiny", out, TINY, latency_iterations=3, minutes=BUDGET_MINUTES)
    assert model.stat().st_mtime_ns == before
    assert set(again["scores"]) == set(summary["scores"])


def test_epochs_fitted_to_the_budget_are_recorded(demo_run: tuple[Path, dict]) -> None:
    out, summary = demo_run
    fit = epoch_budget.load(out)
    assert fit is not None and fit.epochs == summary["epoch_fit"]["epochs"] == summary["settings"]["config"]["train"][
        "epochs"] == 2
    assert fit.budget_s == pytest.approx(60 * BUDGET_MINUTES) and fit.seconds_left < 0
    assert len(fit.first_epoch_seconds) == 4 and all(s > 0 for s in fit.first_epoch_seconds.values())
    assert f"fitted to a {BUDGET_MINUTES:g}-minute budget on this machine" in (out / "report.md").read_text()


def _compare_demos(run_a: Path, run_b: Path) -> subprocess.CompletedProcess[str]:
    """``python -m experiments.compare_demos RUN_A RUN_B``, as a user runs it."""
    return subprocess.run([sys.executable, "-m", "experiments.compare_demos", str(run_a), str(run_b)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_compare_demos_finds_a_changed_number_and_nothing_else(demo_run: tuple[Path, dict], tmp_path: Path) -> None:
    """The tool that shows a restructure kept the demo's numbers: a run against itself has no difference; a copy
    with one score and one learning-curve value changed has exactly those two."""
    out, _ = demo_run
    same = _compare_demos(out, out)
    assert same.returncode == 0, same.stdout + same.stderr
    assert same.stdout.startswith("0 differences") and same.stdout.count("\n") == 1, same.stdout
    copy = Path(shutil.copytree(out, tmp_path / "copy"))
    summary = json.loads((copy / SUMMARY_FILE).read_text())
    scores = summary["scores"][POPCODE]["All objects"]
    scores["MSSD"] += 0.01
    (copy / SUMMARY_FILE).write_text(json.dumps(summary))
    metrics = next((copy / "runs").glob("*/metrics.csv"))
    header, first, *rest = metrics.read_text().splitlines()
    fields = first.split(",")
    fields[1] = repr(float(fields[1]) + 1e-9)  # train_loss of the first epoch
    metrics.write_text("\n".join([header, ",".join(fields), *rest]) + "\n")
    changed = _compare_demos(out, copy)
    assert changed.returncode == 1, changed.stdout + changed.stderr
    count, *differences = changed.stdout.splitlines()
    assert count.startswith("2 differences") and len(differences) == 2, changed.stdout
    assert "All objects.MSSD" in differences[0] and "train_loss" in differences[1]
