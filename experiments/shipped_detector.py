"""Train the shipped detector of the six built-in parts and measure it: AP on a validation and an unseen bin split,
the bin's MSSD end to end from its boxes beside the true and detector-like boxes, and the whole frame's latency.

    python -m experiments.shipped_detector [--work runs/shipped_detector] [--epochs 40] [--scenes 600 900]
        [--empty-scenes 0] [--traced-scenes 0 0 [0 0]] [--traced-samples 8] [--snapshot-every 5]
        [--set detector.KEY=VALUE ...] [--resized-start | --start-from CHECKPOINT]
        [--copy-to models/builtin-parts-detector.onnx] [--best-snapshot] [--measure-only] [--name shipped-detector]

Renders the training scenes (seed 21 without a sensor model, seed 22 with the industrial camera's noise, blur
and exposure, as the demo's scenes; the sizes given by ``--scenes``, whose third and fourth numbers add seeds
24 and 25 likewise; ``--empty-scenes`` bins without parts, seed
23 with the industrial camera, half of them with distractors; ``--traced-scenes N M``: N bins of seed 26 and M
empty bins of seed 27, industrial camera, rendered and then path traced by ``popcode-train path-trace`` at
``--traced-samples`` samples a pixel, the traced copies trained on; a third and fourth number add seeds 28 and 29
likewise), a validation bin split (seed 4000,
industrial, 60 scenes: the project's cluttered validation seed) and the unseen bin split the shipped pose
models are scored on (seed 6002, industrial, 30 scenes: ``models/README.md``); trains ``popcode-train
train-detector`` for ``--epochs`` (rerun to resume: every step keeps what it finished); exports; scores the
detector on both bin splits (COCO AP as the BOP toolkit) and the shipped pose models from its boxes
(``popcode run``'s loop, matched by score as the toolkit does), and AP on the validation split of every
snapshot in ``WORK/snapshots`` (the checkpoint copied every ``--snapshot-every`` epochs while the run goes; a run
with ``detector.ema_decay`` is scored with its averaged and its last step's weights). Writes
``bench/results/NAME.{json,md}`` (``--name``, ``shipped-detector`` by default); the whole frame's latency is
``bench.frame_latency``'s. ``--resized-start``: a run of another input size (``--set detector.input_width=...``)
starts from the shipped detector start of the default size, its weights re-keyed to this size (a convolutional
network's weights do not depend on its input's size; ``detector.init`` "auto" would find no start of this shape),
so that an input size is compared at the same start. ``--start-from``: the run starts from a trained detector's
checkpoint (its averaged weights but the class logits, saved as a detector start), so that a detector goes on
training on other scenes. ``--best-snapshot``: the file scored (and copied by
``--copy-to``) is the snapshot of the highest validation AP on the curve rather than the run's end (early
stopping, chosen on the validation split only).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from popcode_runtime.base.files import copy_file_atomic, write_bytes_atomic
from popcode_runtime.bop.split import split_images
from popcode_runtime.commands.detect import detect_split
from popcode_runtime.inference.detector import Detector
from popcode_trainer.commands.train_detector import detector_config
from popcode_trainer.data.box_noise import box_noise_preset
from popcode_trainer.demo.detector_step import score_own_detector
from popcode_trainer.detection.config import DetectorConfig
from popcode_trainer.detection.export import export_detector, load_detector
from popcode_trainer.detection.start import DETECTOR_START, detector_shape, resolve_detector_start, write_detector_start
from popcode_trainer.eval.pipeline.detector_boxes import with_detector_boxes
from popcode_trainer.eval.pipeline.evaluate import MethodResult, evaluate_models
from popcode_trainer.eval.pipeline.models import Method, load_model
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.detection_scores import detection_scores
from popcode_trainer.train.checkpoint import load
from popcode_trainer.train.pretrained import save_start
from tools.command import run_command
from tools.paths import RESULTS, SHIPPED_MODELS
from tools.report import machine, machine_line, write_results

# the training scenes' seeds in pairs: the first without a sensor model, the second with the industrial camera's
TRAIN_SEEDS = (21, 22, 24, 25)
EMPTY_SEED = 23  # the bins without parts (--empty-scenes)
TRACED_SEEDS = (26, 27, 28, 29)  # path-traced bins in pairs, with parts and without (--traced-scenes)
SPLITS = {"validation": (4000, 60), "unseen": (6002, 30)}  # seed, scenes (industrial camera)


def render_scenes(out: Path, scenes: int, seed: int, sensor: str, empty_share: float = 0.0) -> Path:
    """A bin split of the built-in parts (``popcode-train render --scenes``, ``empty_share`` of them without parts),
    rendered once into ``out``."""
    if not (out / "000000" / "scene_gt.json").is_file():
        subprocess.run([sys.executable, "-m", "popcode_trainer.cli", "render", "--objects", "builtin", "--out",
                        str(out), "--scenes", str(scenes), "--seed", str(seed), "--sensor", sensor, "--quiet",
                        *(["--empty-share", f"{empty_share:g}"] if empty_share else [])], check=True)
    return out


def trace_scenes(source: Path, out: Path, samples: int) -> Path:
    """``source`` path traced into ``out`` (``popcode-train path-trace``; a rerun skips the images it finished)."""
    subprocess.run([sys.executable, "-m", "popcode_trainer.cli", "path-trace", "--split", str(source), "--out",
                    str(out), "--samples", str(samples), "--quiet"], check=True)
    return out


SCORE_KEYS = ("AP", "AP50", "AP75", "recall_30")  # validation_scores' fields, in the tables' order


def run_training(folder: Path) -> dict[str, float]:
    """A detector run's epochs, training seconds, first epoch and best and last validation loss (its metrics)."""
    with (folder / "metrics.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    return {"epochs": len(rows), "training_s": sum(float(row["seconds"]) for row in rows),
            "first_epoch_s": float(rows[0]["seconds"]), "best_val_loss": min(float(row["val_loss"]) for row in rows),
            "last_val_loss": float(rows[-1]["val_loss"])}


def validation_scores(detector: Path, split_dir: Path) -> dict[str, float]:
    """A detector file's COCO AP, AP50, AP75 (as the BOP toolkit scores 2-D detection) and recall of instances
    at least 30 % visible on a split."""
    scores = detection_scores(split_dir, detect_split(Detector(detector), split_images(split_dir), progress=False))
    return {**{key: scores.coco[key] for key in SCORE_KEYS[:3]}, "recall_30": scores.recall_goal.recall}


def score_cells(record: dict[str, Any]) -> list[str]:
    """A record's :data:`SCORE_KEYS` as percentages for a table row."""
    return [f"{100 * record[key]:.1f}" for key in SCORE_KEYS]


def _mssd(result: MethodResult) -> dict[str, Any]:
    return {"MSSD": result.groups["All objects"]["MSSD"], "per_object": {
        name: values["MSSD"] for name, values in result.groups.items() if name != "All objects"},
        "by_visibility": {label: values["MSSD"] for label, values in result.by_visibility.items()}}


def _score_split(detector: Path, split_dir: Path, work: Path) -> dict[str, Any]:
    split = read_eval_split([split_dir], split_dir / "models")
    method = Method("popcode", tuple(load_model(path) for path in SHIPPED_MODELS))
    true_boxes = evaluate_models([method], split, vsd=False)[0]
    noisy = evaluate_models([method], with_detector_boxes(split, box_noise_preset("detector"), seed=0), vsd=False)[0]
    own = score_own_detector(detector, list(SHIPPED_MODELS), split_dir, split, work, "popcode, own detector")
    return {"detection": own.detection.to_dict(), "mean_detect_ms": own.mean_detect_ms,
            "mssd": {"true boxes": _mssd(true_boxes), "detector-like boxes": _mssd(noisy),
                     "own detector": None if own.poses is None else _mssd(own.poses)}}


def resized_start(overrides: list[str], path: Path) -> Path:
    """The shipped start of the default detector's shape, saved at ``path`` as a start of the shape ``overrides``
    give (the same network at another input size)."""
    start, _ = resolve_detector_start(DetectorConfig())
    if start is None:
        raise SystemExit("no shipped detector start of the default shape to resize")
    shape = detector_shape(detector_config(overrides))
    def network(fields: dict[str, Any]) -> str:
        return json.dumps({k: v for k, v in fields.items() if not k.startswith("input_")}, sort_keys=True)

    if network(shape) != network(start.network):
        raise SystemExit(f"--resized-start needs the default network at another input size, got {shape}")
    return save_start(DETECTOR_START, shape, start.state, path, {**start.card, "resized_from": str(start.path)})


def checkpoint_start(checkpoint: Path, path: Path) -> Path:
    """A trained detector's averaged weights (all but its class logits) saved as a start at ``path``."""
    model, config, _ = load_detector(checkpoint, averaged=True)
    return write_detector_start(model, config, path, {"from_checkpoint": str(checkpoint)})


def _train_with_snapshots(command: list[str], run: Path, snapshots: Path, every: int) -> None:
    """Run the training ``command``, copying its checkpoint to ``snapshots/epoch<N>.pt`` at every ``every``-th
    epoch it reaches (polled; a checkpoint is replaced by rename, so a copy is always whole)."""
    process = subprocess.Popen(command)
    while process.poll() is None:
        time.sleep(10)
        _snapshot(run / "detector.pt", snapshots, every)
    if process.returncode:
        raise subprocess.CalledProcessError(process.returncode, command)


def _snapshot(checkpoint: Path, snapshots: Path, every: int) -> None:
    try:
        data = checkpoint.read_bytes()
    except FileNotFoundError:
        return
    epoch = int(torch.load(io.BytesIO(data), weights_only=False)["epoch"])
    target = snapshots / f"epoch{epoch}.pt"
    if epoch % every == 0 and not target.exists():
        snapshots.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(target, data)


def _curve(work: Path, split_dir: Path) -> list[dict[str, Any]]:
    """AP on the validation split of each snapshot a run left in ``WORK/snapshots`` (a run in progress, its rate
    not yet annealed) and of its end, against its training minutes; a run that averages its weights twice: the
    average and the last step's weights (``last_step``)."""
    seconds = np.cumsum([float(row.split(",")[3]) for row in (work / "run" / "metrics.csv").read_text().split()[1:]])
    points: list[dict[str, Any]] = []
    for checkpoint in [*sorted((work / "snapshots").glob("epoch*.pt"), key=lambda p: int(p.stem[5:])),
                       work / "run" / "detector.pt"]:
        state = load(checkpoint)
        epoch = int(state["epoch"])
        if points and points[-1]["epoch"] == epoch:  # the run's end, snapshotted already
            continue
        point: dict[str, Any] = {"epoch": epoch, "minutes": float(seconds[epoch - 1] / 60)}
        for averaged in (True, False) if "ema" in state else (True,):
            onnx_path = checkpoint.with_name(f"{checkpoint.stem}{'' if averaged else '-last-step'}.onnx")
            export_detector(checkpoint, onnx_path, averaged=averaged)
            scores = validation_scores(onnx_path, split_dir)
            point.update({**scores, "file": str(onnx_path)} if averaged else {"last_step": scores})
        points.append(point)
    return points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("runs/shipped_detector"))
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--scenes", type=int, nargs="+", default=(600, 900), metavar="N",
                        help="training scenes of seeds 21 (plain) and 22 (industrial camera), then optionally of "
                             "seeds 24 and 25 likewise: two or four numbers")
    parser.add_argument("--empty-scenes", type=int, default=0, help="bins without parts among the training scenes")
    parser.add_argument("--traced-scenes", type=int, nargs="+", default=(0, 0), metavar="N",
                        help="path-traced training bins with parts (seed 26) and without (seed 27), then optionally "
                             "seeds 28 and 29 likewise: two or four numbers")
    parser.add_argument("--traced-samples", type=int, default=8, help="the path tracer's samples a pixel")
    parser.add_argument("--snapshot-every", type=int, default=5, help="epochs between the curve's snapshots")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="detector.KEY=VALUE")
    parser.add_argument("--resized-start", action="store_true",
                        help="start from the default-size detector start re-keyed to this run's input size")
    parser.add_argument("--start-from", type=Path, metavar="CHECKPOINT",
                        help="start from a trained detector checkpoint's averaged weights (not its class logits)")
    parser.add_argument("--copy-to", type=Path, help="copy the exported detector here")
    parser.add_argument("--best-snapshot", action="store_true",
                        help="score and copy the snapshot (or end) of the highest validation AP on the curve, not "
                             "the run's end: a run that overfits its scenes as its rate anneals is stopped early")
    parser.add_argument("--measure-only", action="store_true", help="score the detector already in WORK/run")
    parser.add_argument("--name", default="shipped-detector", help="the results' name in bench/results (a "
                        "candidate's beside the shipped detector's)")
    args = parser.parse_args()
    if len(args.scenes) not in (2, 4):
        parser.error(f"--scenes takes two or four numbers, got {len(args.scenes)}")
    if len(args.traced_scenes) not in (2, 4):
        parser.error(f"--traced-scenes takes two or four numbers, got {len(args.traced_scenes)}")
    work = args.work
    train = [render_scenes(work / f"train_{seed}", scenes, seed, sensor) for seed, scenes, sensor
             in zip(TRAIN_SEEDS, args.scenes, ("none", "industrial") * 2, strict=False)]
    if args.empty_scenes:
        train.append(render_scenes(work / "train_empty", args.empty_scenes, EMPTY_SEED, "industrial", 1.0))
    for seed, scenes, empty_share in zip(TRACED_SEEDS, args.traced_scenes, (0.0, 1.0) * 2, strict=False):
        if scenes:
            kind = "empty_" if empty_share else ""
            source = render_scenes(work / f"source_{kind}{seed}", scenes, seed, "industrial", empty_share)
            train.append(trace_scenes(source, work / f"traced_{kind}{seed}", args.traced_samples))
    splits = {name: render_scenes(work / name, scenes, seed, "industrial")
              for name, (seed, scenes) in SPLITS.items()}
    run = work / "run"
    started = time.perf_counter()
    if args.resized_start:
        start = resized_start(args.overrides, work / "detector-start-resized.pt")
        args.overrides.append(f"detector.init={start}")
    elif args.start_from:
        start = checkpoint_start(args.start_from, work / "detector-start-from-checkpoint.pt")
        args.overrides.append(f"detector.init={start}")
    if not args.measure_only:
        _train_with_snapshots([sys.executable, "-m", "popcode_trainer.cli", "train-detector", *(
            item for split in train for item in ("--split", str(split))), "--out", str(run), "--set",
            f"detector.epochs={args.epochs}", *(item for o in args.overrides for item in ("--set", o))], run,
            work / "snapshots", args.snapshot_every)
    curve = _curve(work, splits["validation"])
    chosen = max(curve, key=lambda point: point["AP"]) if args.best_snapshot else curve[-1]
    detector = Path(chosen["file"])
    if args.copy_to:
        copy_file_atomic(detector, args.copy_to)
    scores = {name: _score_split(detector, split, work / f"scored_{name}") for name, split in splits.items()}
    payload = {"arguments": {k: str(v) for k, v in vars(args).items()}, "train_seconds": time.perf_counter() - started,
               "scores": scores, "curve": curve, "scored_epoch": chosen["epoch"], "scored_file": str(detector)}
    write_results(RESULTS, args.name, payload, _markdown(payload))


def _scored_line(payload: dict[str, Any]) -> str:
    last = payload["curve"][-1]["epoch"]
    why = "" if payload["scored_epoch"] == last else ", the highest validation AP of the curve: `--best-snapshot`"
    return f"Scored below: the weights of epoch {payload['scored_epoch']} of {last} (`{payload['scored_file']}`{why})."


def _markdown(payload: dict[str, Any]) -> str:
    rows, mssd_rows = [], []
    for name, found in payload["scores"].items():
        det = found["detection"]
        rows.append([name, *(f"{100 * (det.get(k) or 0):.1f}" for k in ("AP", "AP50", "AP75", "AR100")),
                     f"{100 * det['recall_iou50_goal']['recall']:.1f}", f"{found['mean_detect_ms']:.0f}"])
        for boxes, scored in found["mssd"].items():
            if scored is not None:
                mssd_rows.append([name, boxes, f"{100 * scored['MSSD']:.1f}",
                                  *(f"{100 * v:.1f}" for v in scored["by_visibility"].values())])
    bins = list(next(iter(payload["scores"].values()))["mssd"]["true boxes"]["by_visibility"])
    last_step = any("last_step" in p for p in payload["curve"])
    curve = markdown_table(
        ["epoch", "training minutes (2 cores)", "AP", "AP50", "recall ≥ 30 % visible",
         *(["AP, last step's weights", "recall, last step's weights"] if last_step else [])],
        [[str(p["epoch"]), f"{p['minutes']:.0f}", f"{100 * p['AP']:.1f}", f"{100 * p['AP50']:.1f}",
          f"{100 * p['recall_30']:.1f}", *([f"{100 * p['last_step']['AP']:.1f}",
                                            f"{100 * p['last_step']['recall_30']:.1f}"] if last_step else [])]
         for p in payload["curve"]])
    return "\n\n".join([
        "# The shipped detector (`python -m experiments.shipped_detector`)",
        _scored_line(payload),
        markdown_table(["bin split", "AP", "AP50", "AP75", "AR100", "recall ≥ 30 % visible", "ms/frame"], rows),
        "AP on the validation split as the run went (snapshots of the run in progress; its rate falls on a cosine "
        "to zero at its last epoch):",
        curve,
        "MSSD of the shipped pose models (argmax) by where the boxes came from (own detector: every instance, a "
        "missed one wrong, matched by score as the BOP toolkit does):",
        markdown_table(["bin split", "boxes", "MSSD", *(f"visib {b}" for b in bins)], mssd_rows),
        "ms/frame: the detector's own seconds per frame in `popcode detect` (all cores). The whole frame, "
        "detector and ten parts' poses: bench/results/frame-latency.md (`python -m bench.frame_latency`).",
        machine_line(machine()),
    ])


if __name__ == "__main__":
    run_command("experiments.shipped_detector", main)
