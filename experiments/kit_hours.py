"""What the hours buy: kits made with different ``--hours`` scored on one common validation split set.

    python -m experiments.kit_hours KIT [KIT ...] --objects DIR [--work DIR] [--images 100] [--scenes 100]
        [--name NAME]

Each kit's card scores it on test splits of its own, whose size grows with the budget; to compare budgets,
every kit here is scored on the same splits of the same parts, rendered once into ``--work`` with seeds no kit
renders with (a kit's training uses its seed 0, 3000 and 7000, its tests 1000 and 2000): ``--images`` clean
single-part images a part (seed 5000) and ``--scenes`` bin scenes (seed 4000, the industrial camera). Per kit:
the shipped pose files from true boxes (clean and bin, argmax), from the kit's own detector on the bin frames
(a missed part counts as wrong) and the detector's COCO AP, beside the minutes each of the kit's steps took and
the epochs it fitted; a kit of ``experiments.kit_share`` is named by its detector's share of the budget. Results:
``bench/results/kit-hours-<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.demo.detector_step import score_own_detector
from popcode_trainer.demo.files import SUMMARY_FILE
from popcode_trainer.demo.parts import load_parts
from popcode_trainer.eval.pipeline.evaluate import MethodResult, evaluate_models
from popcode_trainer.eval.pipeline.models import Method, load_model
from popcode_trainer.eval.pipeline.split import EvalSplit, read_eval_split
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.kit.budget import DETECTOR_SHARE
from popcode_trainer.kit.layout import DETECTOR_NAME
from popcode_trainer.kit.run import KIT_FILE, WORK_FOLDER
from tools.command import run_command
from tools.experiment import CLEAN_VALIDATION_SEED, CLUTTERED_VALIDATION_SEED
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

ALL = "All objects"


def common_splits(objects: Path, work: Path, images: int, scenes: int) -> tuple[EvalSplit, EvalSplit, Path]:
    """The clean and bin validation splits of ``objects`` (rendered once; a rerun reads them back) and the bin's
    folder, which the detector reads frame by frame."""
    parts = load_parts(objects)
    clean_dir = parts.render_split(work / "clean", images, CLEAN_VALIDATION_SEED, progress=True)
    bin_dir = parts.render_scenes(work / "bin", scenes, CLUTTERED_VALIDATION_SEED, progress=True)
    return (read_eval_split([clean_dir], clean_dir / BUILTIN_MODELS_FOLDER),
            read_eval_split([bin_dir], bin_dir / BUILTIN_MODELS_FOLDER), bin_dir)


def _scores(result: MethodResult | None) -> dict[str, Any] | None:
    if result is None:
        return None
    return {"MSSD": result.groups[ALL]["MSSD"], "MSPD": result.groups[ALL]["MSPD"],
            "per_object_MSSD": {str(o): s["MSSD"] for o, s in sorted(result.per_object.items())},
            "by_visibility_MSSD": {k: v.get("MSSD") for k, v in result.by_visibility.items()}}


def score_kit(kit: Path, clean: EvalSplit, bin_split: EvalSplit, bin_dir: Path, work: Path) -> dict[str, Any]:
    """One kit's shipped files on the common splits, and what its run spent."""
    record, summary = read_json(kit / KIT_FILE), read_json(kit / WORK_FOLDER / SUMMARY_FILE)
    pose_files = sorted(str(p) for p in kit.glob("parts-*.onnx") if p.name != DETECTOR_NAME)
    if not pose_files:
        raise PopcodeError(f"{kit} holds no parts-*.onnx: is the kit finished?")
    method = Method("kit", tuple(load_model(p) for p in pose_files))
    clean_result = evaluate_models([method], clean, vsd=False)[0]
    bin_result = evaluate_models([method], bin_split, vsd=False)[0]
    own = score_own_detector(kit / DETECTOR_NAME, [Path(p) for p in pose_files], bin_dir, bin_split,
                             work / f"detector-{kit.name}", "kit, own detector")
    steps = summary.get("step_seconds", {})
    return {
        "kit": str(kit), "hours": record["hours"], "wall_minutes": summary["wall_seconds"] / 60.0,
        "detector_share": record.get("detector_share", DETECTOR_SHARE),
        "epochs": summary["settings"]["config"]["train"]["epochs"],
        "train_images_per_object": summary["settings"]["train_images_per_object"],
        "train_scenes": summary["settings"]["train_scenes"], "shipped_kind": record["kit"]["kind"],
        "pose_training_minutes": sum(s for k, s in steps.items() if k.startswith("train population_code")) / 60.0,
        "step_minutes": {k: s / 60.0 for k, s in steps.items()},
        "clean": _scores(clean_result), "bin": _scores(bin_result), "from_frame": _scores(own.poses),
        "detector_AP": own.detection.coco.get("AP"), "detector_recall_30": own.detection.recall_goal.recall,
        "detect_ms": own.mean_detect_ms,
    }


def _budget(row: dict[str, Any]) -> str:
    """A kit's budget, and its detector's share where it is not the shipped one (``experiments.kit_share``)."""
    share = row["detector_share"]
    return f"{row['hours']:g}" + ("" if share == DETECTOR_SHARE else f", detector {100 * share:g} %")


def _percent(value: float | None) -> str:
    return "–" if value is None else f"{100.0 * value:.1f}"


def markdown(rows: Sequence[dict[str, Any]], clean: EvalSplit, bin_split: EvalSplit, command: str) -> str:
    """The results page: one row a kit, its per-part scores and its steps' minutes."""
    table = markdown_table(
        ["--hours", "wall min", "pose training min", "epochs", "images a part / bin scenes", "kind",
         "clean MSSD", "bin MSSD (true boxes)", "bin from the frame", "detector AP", "detector recall ≥ 30 %"],
        [[_budget(r), f"{r['wall_minutes']:.1f}", f"{r['pose_training_minutes']:.1f}", str(r["epochs"]),
          f"{r['train_images_per_object']} / {r['train_scenes']}", r["shipped_kind"],
          _percent(r["clean"]["MSSD"]), _percent(r["bin"]["MSSD"]),
          _percent(r["from_frame"]["MSSD"] if r["from_frame"] else None), _percent(r["detector_AP"]),
          _percent(r["detector_recall_30"])] for r in rows])
    per_part = markdown_table(
        ["--hours", "split", *(f"part {o}" for o in rows[0]["clean"]["per_object_MSSD"])],
        [[_budget(r), split, *(_percent(v) for v in r[split]["per_object_MSSD"].values())]
         for r in rows for split in ("clean", "bin")])
    steps = sorted({k for r in rows for k in r["step_minutes"]}, key=lambda k: -max(
        r["step_minutes"].get(k, 0.0) for r in rows))
    step_table = markdown_table(["step", *(_budget(r) for r in rows)],
                                [[k, *(f"{r['step_minutes'].get(k, 0.0):.1f}" for r in rows)] for k in steps])
    return "\n\n".join([
        "# What a kit's hours buy (issue 63, deliverable 4)",
        f"```bash\n{command}\n```",
        f"Common validation splits (seeds no kit renders with): clean {len(clean.instances)} instances, bin "
        f"{len(bin_split.instances)} instances at least 10 % visible; MSSD is BOP19 recall, argmax, rotation from "
        "the model and translation from the ground truth; from the frame, every instance the detector missed counts "
        "as wrong.",
        table, "MSSD per part:", per_part, "Minutes of each of the kit's steps (its `work/summary.json`):",
        step_table, machine_line(machine()),
    ])


def main(argv: Sequence[str] | None = None) -> None:
    """Score every kit, write the results."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("kits", nargs="+", type=Path, help="finished kit folders (popcode-train kit --out)")
    parser.add_argument("--objects", type=Path, required=True, help="the models folder the kits were made of")
    parser.add_argument("--work", type=Path, default=Path("runs/kit_hours"), help="common splits and detections")
    parser.add_argument("--images", type=int, default=100, help="clean validation images a part")
    parser.add_argument("--scenes", type=int, default=100, help="bin validation scenes")
    parser.add_argument("--name", default="validation-parts", help="bench/results/kit-hours-<name>")
    args = parser.parse_args(argv)
    clean, bin_split, bin_dir = common_splits(args.objects, args.work, args.images, args.scenes)
    rows = sorted((score_kit(k, clean, bin_split, bin_dir, args.work) for k in args.kits),
                  key=lambda r: (r["hours"], r["detector_share"]))
    command = " ".join(["python -m experiments.kit_hours", *(argv if argv is not None else sys.argv[1:])])
    json_path, md_path = write_results(RESULTS, f"kit-hours-{args.name}", {"command": command, "kits": rows},
                                       markdown(rows, clean, bin_split, command))
    print(f"wrote {md_path} and {json_path}")


if __name__ == "__main__":
    run_command("experiments.kit_hours", main)
