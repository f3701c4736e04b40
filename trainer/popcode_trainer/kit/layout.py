"""A finished kit run laid out as the repository's ``models/``: one ONNX pose model per object group
(``parts-<ids>.onnx``, the ids as the run folders name them), the detector (``parts-detector.onnx``),
``samples/`` (one clean test image a part and a bin frame, with ``samples.json``) and the card ``README.md``.

Each group's pose model is copied in the kind that ran faster on this machine at batch 1 (float or the demo's
int8 copy, timed by the demo's latency step): chosen on speed alone, never on the test scores, which the card
reports for the kind it ships.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.files import copy_file_atomic, read_json, write_bytes_atomic, write_json_atomic

from ..data.render import BUILTIN_MODELS_FOLDER
from ..demo.files import SAMPLES_FILE
from ..demo.report import POPCODE, QUANTISATION, network_summary, symmetry_name
from ..eval.pipeline.split import read_eval_split
from ..eval.reporting.markdown import markdown_table
from ..export.model_io import read_onnx_metadata
from ..train.network import NetworkConfig

CARD_FILE = "README.md"
SAMPLES_FOLDER = "samples"
BIN_NAME = "bin"
DETECTOR_NAME = "parts-detector.onnx"
FLOAT = "fp32"
OWN_DETECTOR = "own detector"  # the demo summary's keys
DETECTOR_LIKE = f"{POPCODE}, detector-like boxes"
FROM_FRAME = f"{POPCODE}, own detector"
NOT_MEASURED = (
    "What was measured and what was not: the scores above are this kit's, on its own test splits (rendered with "
    "seeds its training never used). What budgets of 0.2 to 1 hour buy on the popcode project's own validation "
    "parts, and what a larger share for the detector buys, is in its bench/results/kit-hours-validation-parts.md; "
    "budgets above 1 hour are not measured yet (issue 63).")


def model_name(obj_ids: Sequence[int]) -> str:
    """``parts-1-2.onnx``: the ids joined as the demo's run folders join them."""
    return f"parts-{'-'.join(map(str, obj_ids))}.onnx"


def fastest_kind(latency: Sequence[Mapping[str, Any]]) -> str:
    """``fp32`` or the demo's quantised kind, whichever took less at batch 1 end to end (the demo's latency step)."""
    def median(kind: str) -> float:
        return min((r["median_ms"] for r in latency if r["model"] == f"{POPCODE} ({kind})" and r["batch"] == 1
                    and r["stage"] == "end-to-end"), default=math.inf)

    return QUANTISATION if median(QUANTISATION) < median(FLOAT) else FLOAT


def write_kit(summary: Mapping[str, Any], out: Path, command: str, machine: Mapping[str, Any]) -> dict[str, Any]:
    """Copy the demo run's pose models (the faster kind), detector and samples into ``out`` and write the card;
    returns what was written."""
    kind = fastest_kind(summary["latency"])
    sources = summary["models"][POPCODE] if kind == FLOAT else summary["quantised_models"]
    models = []
    for source in map(Path, sources):
        target = out / model_name(sorted(read_onnx_metadata(source).objects))
        copy_file_atomic(source, target)
        models.append(target)
    detector = None
    own = summary["cluttered_scores"].get(OWN_DETECTOR)
    if own is not None:
        detector = out / DETECTOR_NAME
        copy_file_atomic(Path(own["detector"]), detector)
    samples = write_samples(Path(summary["samples"]), Path(summary["report"]).parent, out / SAMPLES_FOLDER)
    card = out / CARD_FILE
    bin_image = read_json(samples).get("bin", {}).get("image")
    write_bytes_atomic(card, card_markdown(summary, models, detector, kind, command, machine, bin_image).encode())
    return {"card": str(card), "models": [str(p) for p in models], "detector": str(detector) if detector else None,
            "kind": kind, "samples": str(samples)}


def write_samples(demo_samples: Path, work: Path, folder: Path) -> Path:
    """The demo's one test image a part, and the first frame of its cluttered test split as ``bin.png`` with its
    camera and every instance at least 10 % visible (as ``models/samples/samples.json`` holds them)."""
    folder.mkdir(parents=True, exist_ok=True)
    samples = read_json(demo_samples)
    for sample in samples["samples"]:
        copy_file_atomic(demo_samples.parent / sample["image"], folder / sample["image"])
    cluttered = work / "test_cluttered"
    if cluttered.is_dir():
        split = read_eval_split([cluttered], cluttered / BUILTIN_MODELS_FOLDER)
        first = split.instances[0].image_path
        instances = [inst for inst in split.instances if inst.image_path == first]
        K = instances[0].K
        image = folder / f"{BIN_NAME}{first.suffix}"
        copy_file_atomic(first, image)
        samples["bin"] = {
            "image": image.name, "K": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
            "note": "the first frame of the kit's cluttered test split, for the detector",
            "instances": [{"obj_id": inst.obj_id, "bbox_obj": [float(v) for v in inst.box],
                           "visib_fract": float(inst.visib_fract), "R_m2c": np.asarray(inst.R_m2c).tolist(),
                           "t_m2c_mm": np.asarray(inst.t_m2c_mm).tolist()} for inst in instances]}
    path = folder / SAMPLES_FILE
    write_json_atomic(path, samples)
    return path


def _percent(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{100.0 * value:.1f} %"


def _row(name: str, scores: Mapping[str, float] | None) -> list[str]:
    scores = scores or {}
    return [name, *(_percent(scores.get(metric)) for metric in ("MSSD", "MSPD", "ADI"))]


def _all(groups: Mapping[str, Any] | None) -> Mapping[str, float] | None:
    """The "All objects" scores of a method's groups (None: not scored)."""
    return None if groups is None else groups["All objects"]


def _cluttered(entry: Mapping[str, Any] | None) -> Mapping[str, float] | None:
    return None if entry is None else _all(entry["groups"])


def _files_table(models: Sequence[Path], detector: Path | None, kind: str) -> str:
    rows = []
    for path in models:
        meta = read_onnx_metadata(path)
        layout = meta.code
        code = (f"{layout.n_axes} axes (axis-only)" if layout.axis_only
                else f"{layout.n_axes} axes x {layout.n_angles} angles") + f", sigma {layout.sigma_deg:.0f} deg"
        objects = ", ".join(f"{o} ({symmetry_name(meta.objects[o])})" for o in sorted(meta.objects))
        rows.append([f"`{path.name}`", objects, code, kind, f"{path.stat().st_size / 1e6:.1f} MB"])
    if detector is not None:
        rows.append([f"`{detector.name}`", "every part (detector)", "–", FLOAT,
                     f"{detector.stat().st_size / 1e6:.1f} MB"])
    return markdown_table(["file", "objects (symmetry)", "code", "weights", "size"], rows)


def _accuracy(summary: Mapping[str, Any], kind: str) -> str:
    settings, clean, cluttered = summary["settings"], summary["scores"], summary["cluttered_scores"]
    shipped = POPCODE if kind == FLOAT else f"{POPCODE} ({QUANTISATION})"
    rows = [_row(f"clean ({settings['test_images_per_object']} images a part), the shipped files",
                 _all(clean.get(shipped))),
            *([_row("clean, float copies", _all(clean.get(POPCODE)))] if kind != FLOAT else []),
            _row("clean, float copies, refined decoder", _all(clean.get(f"{POPCODE} (refined)")))]
    if cluttered:
        scenes = settings["cluttered_test_scenes"]
        rows += [_row(f"bin ({scenes} scenes), true boxes, float copies", _cluttered(cluttered.get(POPCODE))),
                 _row("bin, detector-like boxes (IoU about 0.75)", _cluttered(cluttered.get(DETECTOR_LIKE))),
                 _row("bin, from the frame: the kit's detector's boxes", _cluttered(cluttered.get(FROM_FRAME)))]
    traced = summary.get("path_traced_scores") or {}
    if "path_traced" in traced:
        rows += [_row(f"clean, first {settings['path_traced_images']} images a part as rendered",
                      _all(traced["rendered"])),
                 _row("the same images path traced", _all(traced["path_traced"]))]
    lines = [markdown_table(["test split (BOP19 recall, argmax)", "MSSD", "MSPD", "ADI"], rows)]
    if "skipped" in traced:
        lines.append(f"Path-traced test images skipped: {traced['skipped']}")
    own = cluttered.get(OWN_DETECTOR) if cluttered else None
    if own is not None:
        found = own["detection"]["recall_iou50_goal"]
        lines.append(f"The detector on the bin split (COCO AP on amodal boxes, as the BOP toolkit scores 2-D "
                     f"detection): AP {_points(own['detection'].get('AP'))}, AP50 "
                     f"{_points(own['detection'].get('AP50'))}, AP75 {_points(own['detection'].get('AP75'))}; it "
                     f"finds {_percent(found['recall'])} of the {found['instances']} instances at least 30 % visible "
                     f"(IoU 0.5), {own['mean_detect_ms']:.1f} ms a frame.")
    return "\n\n".join(lines)


def _points(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{100.0 * value:.1f}"


def _training(summary: Mapping[str, Any], kind: str) -> str:
    settings = summary["settings"]
    config, fit = settings["config"], summary.get("epoch_fit")
    network = NetworkConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in config["network"].items()})
    box_noise = config["data"]["box_noise"]
    boxes = ("true boxes" if box_noise == "none"
             else f"`{box_noise}` boxes for {100 * config['data']['box_noise_p']:g} % of them")
    traced = (f", {settings['traced_train_images']} path-traced images a part ({100 * settings['traced_share']:g} %)"
              if settings["traced_train_images"] else "")
    epochs = f"{config['train']['epochs']} epochs" + (
        f" (fitted to the budget: one epoch of every model took {sum(fit['first_epoch_seconds'].values()):.0f} s)"
        if fit else "")
    starts = sorted(set(summary.get("first_weights", {}).values()))
    return (f"Rendered {settings['train_images_per_object']} grey 128 x 128 images a part and "
            f"{settings['train_scenes']} bin scenes ({100 * settings['scene_share']:g} % of every epoch's crops)"
            f"{traced}; crops of {boxes}; network {network_summary(network)}; {epochs}, batch "
            f"{config['train']['batch_size']}, lr {config['train']['lr']}, {config['train']['loss']} loss, "
            f"{config['train']['rotation_frame']} rotations. First weights: {'; '.join(starts) or 'not recorded'}. "
            f"The detector trained for {settings['detector_seconds'] / 60:.1f} minutes on the bin scenes. "
            f"Shipped kind: {kind} (faster here at batch 1 than the other; latency below).")


def card_markdown(summary: Mapping[str, Any], models: Sequence[Path], detector: Path | None, kind: str,
                  command: str, machine: Mapping[str, Any], bin_image: str | None) -> str:
    """The kit's model card: files, how to use them, its scores on its own test splits, the machine, the command."""
    samples = read_json(Path(summary["samples"]))["samples"]
    example = models[-1]
    sample = next(s for s in samples if s["obj_id"] in read_onnx_metadata(example).objects)
    box, K = ",".join(f"{v:g}" for v in sample["box"]), ",".join(f"{v:g}" for v in sample["K"])
    usage = [f"popcode info {example.name}",
             f"popcode predict {example.name} {SAMPLES_FOLDER}/{sample['image']} --box {box} --K {K} "
             f"--obj-id {sample['obj_id']} --top-k 2"]
    if detector is not None and bin_image is not None:
        usage.append(f"popcode detect {detector.name} {SAMPLES_FOLDER}/{bin_image}")
    flags = ", ".join(machine.get("cpu_flags", [])) or "no flags read"
    latency = markdown_table(["model", "batch", "stage", "median ms"],
                             [[r["model"], r["batch"], r["stage"], f"{r['median_ms']:.2f}"]
                              for r in summary["latency"]])
    return "\n\n".join([
        f"# Model card: popcode kit of {summary['objects']}",
        f"Made by `{command}` in {summary['wall_seconds'] / 60:.1f} minutes on {machine['cpu']} ({flags}), "
        f"{machine['cores']} cores, load {machine['load_average_1m']:.2f}, training on {machine['device']}; "
        f"Python {machine['python']}, torch {machine['torch']}, onnxruntime {machine['onnxruntime']}. Every model "
        "predicts allocentric rotations: give the camera (`--K`).",
        _files_table(models, detector, kind),
        "```bash\n" + "\n".join(usage) + "\n```",
        f"`{SAMPLES_FOLDER}/` holds one clean test image a part and a bin frame, with their boxes, cameras and "
        f"true poses in `{SAMPLES_FOLDER}/{SAMPLES_FILE}`.",
        "## Training\n\n" + _training(summary, kind),
        "## Accuracy on the kit's own test splits\n\nRotation from the model, translation from the ground truth "
        "(the paper's protocol), instances at least 10 % visible.\n\n" + _accuracy(summary, kind),
        "## Latency (one thread, the largest group's model)\n\n" + latency,
        NOT_MEASURED + " Every table, figure and the run's steps: `work/report.md`.",
    ]) + "\n"
