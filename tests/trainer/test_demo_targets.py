"""The demo's accuracy targets: met/missed from a run's scores, and the learning curve that says why."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from popcode_trainer.demo.targets import held_out_errors, targets, targets_markdown
from popcode_trainer.train.run_files import METRICS_FILE


def _result(name: str, per_object: dict[int, float], ambiguous: float, unambiguous: float,
            overall: float) -> SimpleNamespace:
    """The fields of a MethodResult the targets read."""
    return SimpleNamespace(name=name, per_object={o: {"MSSD": v} for o, v in per_object.items()},
                           groups={"All objects": {"MSSD": overall}, "With ambiguity": {"MSSD": ambiguous},
                                   "Without ambiguity": {"MSSD": unambiguous}})


def _run(folder: Path, medians: list[float]) -> Path:
    folder.mkdir()
    rows = "".join(f"{i + 1},{m}\n" for i, m in enumerate(medians))
    (folder / METRICS_FILE).write_text("epoch,val_error_median_deg\n" + rows)
    return folder


def test_targets_met_and_missed() -> None:
    popcode = _result("population_code", {1: 0.95, 2: 0.9, 6: 0.6}, ambiguous=0.9, unambiguous=0.6, overall=0.86)
    baseline = _result("single_variable", {1: 0.9, 2: 0.8, 6: 0.65}, ambiguous=0.78, unambiguous=0.65, overall=0.8)
    found = {t.name: t for t in targets(popcode, baseline)}
    assert found["MSSD over all parts"].met
    weakest = found["MSSD of the weakest part (object 6)"]
    assert weakest.value == 0.6 and not weakest.met
    assert found["lead over single_variable, parts with ambiguity"].met  # +12
    lead = found["lead over single_variable, parts without ambiguity"]
    assert abs(lead.value + 0.05) < 1e-12 and not lead.met


def test_missed_target_shows_the_learning_curve(tmp_path: Path) -> None:
    popcode = _result("population_code", {3: 0.6}, ambiguous=0.6, unambiguous=float("nan"), overall=0.6)
    learning = _run(tmp_path / "still", [40.0, 30.0, 25.0, 22.0])
    assert held_out_errors(learning) == [40.0, 30.0, 25.0, 22.0]
    text = targets_markdown(popcode, None, [learning])
    assert "**missed**" in text and "| still | 2 | 30.0 deg | 4 | 22.0 deg |" in text
    assert "the limiting factor is training compute" in text
    flat = _run(tmp_path / "flat", [40.0, 30.0, 30.0, 29.5])
    assert "levelled off" in targets_markdown(popcode, None, [flat])


def test_all_met_needs_no_curve(tmp_path: Path) -> None:
    popcode = _result("population_code", {1: 0.9, 2: 0.88}, ambiguous=0.89, unambiguous=float("nan"), overall=0.89)
    text = targets_markdown(popcode, None, [_run(tmp_path / "run", [20.0, 10.0])])
    assert "missed" not in text and "held-out" not in text
