"""A second look on the crop: does a small classifier of each box's crop rescore the detector's boxes better (issue 61)?

    OMP_NUM_THREADS=2 python -m experiments.crop_verifier --split runs/shipped_detector2/validation
        --path-traced runs/pt/validation --train DIR[:IMAGES] [--train ...] [--size 64] [--epochs 8]
        [--detector models/builtin-parts-detector.onnx] [--work runs/crop_verifier] [--name crop-verifier-64]

The crops are the runtime's (``crop_square``, padding 1.2, ``--size`` pixels a side) of the detector's boxes at
score 0.2 on the training splits and of two noisy copies (``box_noise`` preset ``detector``) of every true box,
each labelled with the object of the part it lies on (IoU >= 0.5 with a part at least 10 % visible), background
(IoU < 0.3 with every part) or left out (between). A small network (five strided and plain 3 x 3 convolutions,
16 to 128 channels, global average, one logit per object and one for background) learns them with cross-entropy,
brightness, contrast, gamma and noise jitter and a one-cycle rate, then is exported to ONNX and run by
onnxruntime. On the validation bins (rendered and path traced; no test split is read) the detector's boxes at
0.2 are rescored: the detector's score alone, times the crop's probability of the box's object, and times its
probability of any part (one minus background), each at several thresholds. The crops, the network and its ONNX
file are kept in ``--work`` (a rerun takes them from there). Writes ``bench/results/NAME.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import torch
from torch import nn
from torch.nn import functional
from tqdm import tqdm

from popcode_runtime.bop.detections import Detection
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT, split_images
from popcode_runtime.geometry.crop import crop_square, read_image_file
from popcode_runtime.inference.detector import Detector
from popcode_trainer.data.box_noise import box_iou, box_noise_preset, noisy_box
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.detection_scores import detection_scores, ground_truth_instances
from tools.command import run_command
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

CANDIDATE_SCORE = 0.2  # the detector's boxes the verifier sees
PADDING = 1.2
PART_IOU, BACKGROUND_IOU = 0.5, 0.3
NOISY_COPIES = 2
MODES = ("detector", "detector x object", "detector x part")
THRESHOLDS = (0.1, 0.2, 0.3)


def labelled_crops(detector: Detector, split_dir: Path, size: int, rng: np.random.Generator,
                   max_images: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """uint8 crops ``(N, size, size)`` and labels (object column, or ``len(obj_ids)`` for background)."""
    column = {obj_id: c for c, obj_id in enumerate(detector.obj_ids)}
    background = len(column)
    images = split_images(split_dir)
    _, instances = ground_truth_instances(split_dir, "amodal")
    parts = defaultdict(list)
    for instance in instances:
        parts[instance.image].append(instance)
    noise = box_noise_preset("detector")
    crops, labels = [], []
    for key in tqdm(sorted(images)[:max_images], desc=f"crops of {split_dir.name}", unit="image"):
        image = read_image_file(images[key].path)
        here = parts[key]
        boxes = [d.box for d in detector.detect(image)]
        boxes += [noisy_box(p.box, noise, rng, (image.shape[1], image.shape[0]))
                  for p in here if p.visib_fract >= BOP19_MIN_VISIB_FRACT for _ in range(NOISY_COPIES)]
        for box in boxes:
            ious = [box_iou(box, p.box) for p in here]
            best = int(np.argmax(ious)) if ious else -1
            if best >= 0 and ious[best] >= PART_IOU and here[best].visib_fract >= BOP19_MIN_VISIB_FRACT:
                label = column[here[best].obj_id]
            elif best < 0 or ious[best] < BACKGROUND_IOU:
                label = background
            else:
                continue
            crops.append(np.round(crop_square(image, box, size, PADDING) * 255).astype(np.uint8))
            labels.append(label)
    return np.stack(crops), np.array(labels, np.int64)


class VerifierNet(nn.Module):
    """Grey crop in [0, 1] -> one logit per object and one for background."""

    def __init__(self, classes: int) -> None:
        super().__init__()
        widths = [(1, 16, 2), (16, 32, 1), (32, 32, 2), (32, 64, 1), (64, 64, 2), (64, 128, 1), (128, 128, 2)]
        self.trunk = nn.Sequential(*(nn.Sequential(nn.Conv2d(i, o, 3, s, 1, bias=False), nn.BatchNorm2d(o),
                                                   nn.ReLU(inplace=True)) for i, o, s in widths))
        self.head = nn.Linear(128, classes)

    def forward(self, crops: torch.Tensor) -> torch.Tensor:
        return self.head(self.trunk((crops - 0.45) / 0.25).mean(dim=(2, 3)))


def jitter(crops: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Gamma, contrast, brightness and pixel noise, each drawn per crop."""
    n = len(crops)
    draw = lambda: torch.randn(n, 1, 1, 1, generator=generator)  # noqa: E731
    out = crops.clamp(1e-4, 1.0) ** torch.exp(0.2 * draw())
    out = out * (1 + 0.2 * draw()) + 0.1 * draw()
    out = out + torch.randn(out.shape, generator=generator) * torch.rand(n, 1, 1, 1, generator=generator) * 0.04
    return out.clamp(0.0, 1.0)


def train(crops: np.ndarray, labels: np.ndarray, classes: int, epochs: int, seed: int = 0,
          batch: int = 128) -> tuple[VerifierNet, list[float]]:
    """The network after ``epochs`` over the crops; the training accuracy of each epoch."""
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    model = VerifierNet(classes)
    images, targets = torch.from_numpy(crops), torch.from_numpy(labels)
    steps = len(images) // batch
    optimiser = torch.optim.AdamW(model.parameters(), 2e-3, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, 2e-3, total_steps=epochs * steps, pct_start=0.1)
    accuracies = []
    for _ in tqdm(range(epochs), desc="verifier epochs", unit="epoch"):
        model.train()
        order, right = torch.randperm(len(images), generator=generator), 0
        for step in range(steps):
            pick = order[step * batch:(step + 1) * batch]
            logits = model(jitter(images[pick].float()[:, None] / 255, generator))
            loss = functional.cross_entropy(logits, targets[pick], label_smoothing=0.05)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            schedule.step()
            right += int((logits.argmax(1) == targets[pick]).sum())
        accuracies.append(right / (steps * batch))
    return model.eval(), accuracies


def rescored(detector: Detector, session: ort.InferenceSession, split_dir: Path, size: int
             ) -> tuple[list[tuple[Detection, np.ndarray]], float]:
    """The detector's boxes at :data:`CANDIDATE_SCORE` with the verifier's probabilities, and its ms per crop."""
    column = {obj_id: c for c, obj_id in enumerate(detector.obj_ids)}
    found, seconds, count = [], 0.0, 0
    for key, entry in sorted(split_images(split_dir).items()):
        image = read_image_file(entry.path)
        boxes = detector.detect(image)
        if not boxes:
            continue
        started = time.perf_counter()
        crops = np.stack([crop_square(image, b.box, size, PADDING) for b in boxes])[:, None]
        logits = session.run(None, {"crops": crops})[0]
        seconds, count = seconds + time.perf_counter() - started, count + len(boxes)
        probabilities = np.exp(logits - logits.max(1, keepdims=True))
        probabilities /= probabilities.sum(1, keepdims=True)
        found += [(Detection(*key, b.obj_id, b.box, b.score, 0.0), p[[column[b.obj_id], -1]])
                  for b, p in zip(boxes, probabilities, strict=True)]
    return found, 1000 * seconds / max(count, 1)


def scores(split_dir: Path, found: list[tuple[Detection, np.ndarray]]) -> list[dict[str, Any]]:
    rows = []
    for mode in MODES:
        for threshold in THRESHOLDS:
            kept = []
            for detection, (p_object, p_background) in found:
                value = {"detector": 1.0, "detector x object": p_object, "detector x part": 1 - p_background}[mode]
                score = detection.score * float(value)
                if score >= threshold:
                    kept.append(Detection(detection.scene_id, detection.im_id, detection.obj_id, detection.box, score))
            scored = detection_scores(split_dir, kept)
            rows.append({"mode": mode, "threshold": threshold, "AP": scored.coco["AP"], "AP50": scored.coco["AP50"],
                         "recall_30": scored.recall_goal.recall,
                         "boxes_per_instance": scored.detections / scored.instances})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", type=Path, required=True, help="the rendered validation bin split")
    parser.add_argument("--path-traced", type=Path, help="the same split path traced")
    parser.add_argument("--train", action="append", required=True, metavar="DIR[:IMAGES]",
                        help="a training split, optionally only its first IMAGES images (repeat)")
    parser.add_argument("--detector", type=Path, default=Path("models/builtin-parts-detector.onnx"))
    parser.add_argument("--size", type=int, default=64, help="the crop's side [px]")
    parser.add_argument("--epochs", type=int, default=8)
    parser.add_argument("--work", type=Path, default=Path("runs/crop_verifier"))
    parser.add_argument("--name", default=None, help="the results' name (crop-verifier-SIZE by default)")
    args = parser.parse_args()
    work = args.work / f"size{args.size}"
    work.mkdir(parents=True, exist_ok=True)
    detector = Detector(args.detector, threads=2, score_threshold=CANDIDATE_SCORE)
    crops_file, onnx_file = work / "crops.npz", work / f"verifier-{args.epochs}.onnx"
    if not crops_file.exists():
        rng = np.random.default_rng(0)
        parts = []
        for item in args.train:
            folder, _, limit = item.partition(":")
            parts.append(labelled_crops(detector, Path(folder), args.size, rng, int(limit) if limit else None))
        np.savez(crops_file.with_suffix(".partial.npz"), crops=np.concatenate([p[0] for p in parts]),
                 labels=np.concatenate([p[1] for p in parts]))
        crops_file.with_suffix(".partial.npz").replace(crops_file)
    data = np.load(crops_file)
    classes = len(detector.obj_ids) + 1
    accuracies: list[float] = []
    if not onnx_file.exists():
        started = time.perf_counter()
        model, accuracies = train(data["crops"], data["labels"], classes, args.epochs)
        minutes = (time.perf_counter() - started) / 60
        partial = onnx_file.with_suffix(".partial.onnx")
        torch.onnx.export(model, torch.zeros(1, 1, args.size, args.size), partial, input_names=["crops"],
                          output_names=["logits"], dynamic_axes={"crops": {0: "n"}, "logits": {0: "n"}},
                          dynamo=False)
        partial.replace(onnx_file)
        (work / f"training-{args.epochs}.txt").write_text(f"{minutes:.1f} min, accuracy by epoch {accuracies}\n")
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(onnx_file, options, providers=["CPUExecutionProvider"])
    splits = {"rendered": args.split, **({"path-traced": args.path_traced} if args.path_traced else {})}
    rows = []
    for split_name, split_dir in splits.items():
        found, ms_per_crop = rescored(detector, session, split_dir, args.size)
        rows.append({"split": split_name, "ms_per_crop": ms_per_crop, "rows": scores(split_dir, found)})
    payload = {"command": shlex.join(["python", "-m", "experiments.crop_verifier", *sys.argv[1:]]),
               "threads": os.environ.get("OMP_NUM_THREADS"), "size": args.size, "epochs": args.epochs,
               "crops": len(data["labels"]), "label_counts": np.bincount(data["labels"], minlength=classes).tolist(),
               "training": (work / f"training-{args.epochs}.txt").read_text().strip(), "splits": rows}
    write_results(RESULTS, args.name or f"crop-verifier-{args.size}", payload, _markdown(payload))


def _markdown(payload: dict[str, Any]) -> str:
    table = markdown_table(
        ["split", "score", "threshold", "AP", "AP50", "recall ≥ 30 % visible", "boxes / instance"],
        [[split["split"], row["mode"], f"{row['threshold']:g}",
          *(f"{100 * row[k]:.1f}" for k in ("AP", "AP50", "recall_30")), f"{row['boxes_per_instance']:.2f}"]
         for split in payload["splits"] for row in split["rows"]])
    cost = ", ".join(f"{s['split']} {s['ms_per_crop']:.2f} ms" for s in payload["splits"])
    return "\n\n".join([
        f"# A second look on the crop, {payload['size']} px (`python -m experiments.crop_verifier`)",
        f"Command: `{payload['command']}` (OMP_NUM_THREADS={payload['threads']}); validation splits only (the bin of "
        "seed 4000, industrial camera, and its path-traced copy).",
        f"Training: {payload['crops']} crops (per object and background: {payload['label_counts']}), "
        f"{payload['epochs']} epochs; {payload['training']}.",
        "The detector's boxes at 0.2, scored by the detector alone, times the crop's probability of the box's object, "
        "or times its probability of any part; kept at the threshold:",
        table,
        f"The crop and the verifier, ms a box on one thread (crop, network, batched per frame): {cost}.",
        machine_line(machine())])


if __name__ == "__main__":
    run_command("experiments.crop_verifier", main)
