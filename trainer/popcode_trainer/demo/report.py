"""What a demo run leaves for its reader: the one-page report, the model card, sample images and the summary."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT
from popcode_runtime.inference.benchmark import BENCH_IMAGE_SHAPE, machine_description
from popcode_runtime.model.metadata import Representation, RotationFrame

from ..eval.pipeline.evaluate import MethodResult
from ..eval.pipeline.split import EvalSplit
from ..eval.reporting.confidence import RELIABILITY_PNG, confidence_markdown
from ..eval.reporting.markdown import markdown_table
from ..eval.reporting.report import REPORT_MD
from ..eval.reporting.sections import full_pose_markdown
from ..eval.reporting.tables import ambiguity_markdown, methods_markdown, to_json
from ..export.model_io import read_onnx_metadata
from ..train.config import DataConfig
from ..train.fast_path import StepPath
from ..train.network import NetworkConfig
from .detector_section import own_detector_markdown
from .detector_step import DETECTIONS_FILE, DETECTOR_STAGE, OWN_DETECTOR_FOLDER, OwnDetectorResults
from .epoch_budget import EpochFit
from .files import MODEL_CARD_FILE, REPORT_FILE, SAMPLES_FILE, SUMMARY_FILE
from .look_alike_section import look_alike_markdown
from .path_traced_section import path_traced_markdown, path_traced_summary
from .path_traced_step import TRACED_FOLDER, PathTracedResults
from .start_section import first_weights, first_weights_text
from .steps import PipelineSize
from .targets import DETECTOR_TARGET, clutter_targets, targets_markdown, targets_table

POPCODE = Representation.POPULATION_CODE
QUANTISATION = "int8"


@dataclass(frozen=True)
class TrainedModels:
    """ONNX files per representation (one per object group) and the population code's quantised ones."""

    by_representation: dict[str, list[Path]]
    quantised: list[Path]


@dataclass(frozen=True)
class ClutteredResults:
    """The methods on the cluttered test split with ground-truth boxes, and the population code with a detector's."""

    methods: list[MethodResult]
    detector_boxes: MethodResult | None = None
    own_detector: OwnDetectorResults | None = None  # the run's own detector, its boxes and the poses in them


@dataclass(frozen=True)
class DemoRun:
    """Everything a finished demo produced, for the files that describe it."""

    size_name: str
    size: PipelineSize
    groups: list[list[int]]
    out_dir: Path
    models: TrainedModels
    split: EvalSplit
    results: list[MethodResult]
    latency: list[dict[str, Any]]
    figures: dict[str, list[Path]]
    step_seconds: dict[str, float]
    cluttered: ClutteredResults | None = None  # the same methods on the cluttered test split
    epoch_fit: EpochFit | None = None  # how the epochs were fitted to a time budget, when they were
    parts: str = "the six built-in parts"  # what was rendered, as the texts name it (demo.parts.Parts.describe)
    objects_option: str = ""  # the `popcode-train demo` option that selects those parts (empty: the built-in ones)
    code_notes: tuple[str, ...] = ()  # per object group, the code it trained with and why (demo.group_codes)
    render_note: str = ""  # how the single-part renders frame the parts, where not as the renderer does by default
    path_traced: PathTracedResults | None = None  # the first test images path traced, where the size asks for it

    @property
    def seconds(self) -> float:
        return sum(self.step_seconds.values())

    def link(self, path: Path) -> str:
        """``path`` relative to the run folder, as the report links it."""
        return os.path.relpath(path, self.out_dir)


def latency_markdown(records: Sequence[dict[str, Any]]) -> str:
    rows = [(r["model"], f"{r['megabytes']:.1f}", r["batch"], r["stage"], f"{r['median_ms']:.2f}", f"{r['p90_ms']:.2f}",
             f"{1000 * r['batch'] / r['median_ms']:.0f}") for r in records]
    return markdown_table(["model", "MB", "batch", "stage", "median ms", "p90 ms", "crops/s"], rows)


def symmetry_name(info: dict[str, Any]) -> str:
    if info.get("symmetries_continuous"):
        return "continuous" + (" + flip" if info.get("symmetries_discrete") else "")
    count = len(info.get("symmetries_discrete", []))
    return "no symmetry" if count == 0 else f"{count + 1} symmetric poses"


def network_summary(network: NetworkConfig) -> str:
    """The trunk's widths in a few words; 'paper size' for the paper's."""
    if network == NetworkConfig(output_dim=network.output_dim, input_size=network.input_size):
        return "paper size"
    return (f"{network.trunk} trunk, conv {list(network.conv_channels)}, squeeze {network.squeeze_channels}, "
            f"hidden {list(network.hidden)}")


def write_model_card(run: DemoRun) -> Path:
    """What a user of the population-code models needs: objects, symmetry, data, accuracy, speed, how to rebuild."""
    size = run.size
    train, network = size.config.train, size.config.network
    lines = [f"# Model card: population-code models of {_card_subject(run)} (demo size `{run.size_name}`)", ""]
    for path, quantised in zip(run.models.by_representation[POPCODE], run.models.quantised, strict=True):
        meta = read_onnx_metadata(path)
        objects = ", ".join(f"{o} ({symmetry_name(meta.objects[o])})" for o in sorted(meta.objects))
        layout = meta.code
        lines.append(f"- `{run.link(path)}`: objects {objects}; code {layout.n_axes} axes"
                     + ("" if layout.axis_only else f" x {layout.n_angles} angles")
                     + f", sigma {layout.sigma_deg:.0f} deg; {meta.rotation_frame} rotation; "
                     f"{path.stat().st_size / 1e6:.1f} MB ({QUANTISATION}: {quantised.stat().st_size / 1e6:.1f} MB)")
    lines += [
        "",
        "## Training",
        f"Rendered grey 128 x 128 images of {run.parts} (random rotation, position and lighting; "
        f"`popcode_trainer.data.render`), {size.train_images_per_object} per object, the paper's augmentation"
        f"{_scenes_text(size)}, {_training_boxes_text(size.config.data)}; "
        f"{train.epochs} epochs, batch {train.batch_size}, Adam lr {train.lr}, {train.loss} loss on the code; "
        f"network {network_summary(network)}." + (f" {run.render_note}" if run.render_note else ""),
        *(["", *_code_lines(run)] if run.code_notes else []),
        "",
        f"## Accuracy (all objects; {size.test_images_per_object} rendered test images per object, other seed; "
        "rotation from the model, translation from the ground truth)",
        "",
        methods_markdown({r.name: r.groups["All objects"] for r in run.results}),
        "",
        "## Latency (one thread)",
        "",
        latency_markdown(run.latency),
        "",
        f"Measured on: {machine_description()['cpu']}, {os.cpu_count()} cores.",
        "",
        "## Reproduce",
        "",
        f"`popcode-train demo --size {run.size_name}{run.objects_option} --out DIR`; the models are "
        "`DIR/runs/population_code_*/model*.onnx`.",
    ]
    path = run.out_dir / MODEL_CARD_FILE
    write_bytes_atomic(path, ("\n".join(lines) + "\n").encode())
    return path


def write_samples(split: EvalSplit, out_dir: Path) -> Path:
    """One test image per object with its box, camera and true pose (``samples.json``): what a runtime user
    needs to try a model with ``popcode predict`` and compare with the truth."""
    out_dir.mkdir(parents=True, exist_ok=True)
    samples = []
    for obj_id in split.obj_ids:
        inst = next(inst for inst in split.instances if inst.obj_id == obj_id)
        image = out_dir / f"obj{obj_id:02d}{inst.image_path.suffix}"
        write_bytes_atomic(image, inst.image_path.read_bytes())
        K = inst.K
        samples.append({"image": image.name, "obj_id": obj_id, "box": [float(v) for v in inst.box],
                        "K": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
                        "R_m2c": np.asarray(inst.R_m2c).tolist(), "t_m2c_mm": np.asarray(inst.t_m2c_mm).tolist()})
    path = out_dir / SAMPLES_FILE
    write_bytes_atomic(path, (to_json({"samples": samples}) + "\n").encode())
    return path


def _demote_headings(markdown: str) -> str:
    return "\n".join("#" + line if line.startswith("#") else line for line in markdown.splitlines())


def _file_links(run: DemoRun, paths: Sequence[Path]) -> str:
    return ", ".join(f"[`{run.link(p)}`]({run.link(p)})" for p in paths)


def report_markdown(run: DemoRun, model_card: Path) -> str:
    """The run's one-page report, with links relative to the run folder."""
    size, machine = run.size, machine_description()
    model_lines = [f"- {name}: {_file_links(run, paths)}" for name, paths in run.models.by_representation.items()]
    model_lines.append(f"- {POPCODE} ({QUANTISATION}): {_file_links(run, run.models.quantised)}")
    figure_lines = [f"### {title}\n\n" + "\n".join(f"![{title}]({run.link(p)})" for p in paths)
                    for title, paths in run.figures.items()]
    example = run.models.by_representation[POPCODE][-1]
    example_metadata = read_onnx_metadata(example)
    example_objects = example_metadata.objects
    instance = next(inst for inst in run.split.instances if inst.obj_id in example_objects)
    box = ",".join(f"{v:g}" for v in instance.box)
    camera = (f" --K {instance.K[0, 0]:g},{instance.K[1, 1]:g},{instance.K[0, 2]:g},{instance.K[1, 2]:g}"
              if example_metadata.rotation_frame == RotationFrame.ALLOCENTRIC else "")
    eval_report = run.out_dir / "eval" / REPORT_MD
    return "\n\n".join(part for part in [
        f"# popcode demo (`--size {run.size_name}`)",
        f"Rendered {run.parts} ({size.train_images_per_object} training and "
        f"{size.test_images_per_object} test images per object{_scenes_text(size)}), trained "
        f"{', '.join(size.representations)} on {_training_boxes_text(size.config.data)} "
        f"with the same network, data and budget ({_epochs_text(run)}; objects pooled as {run.groups}), "
        f"exported ONNX (float and {QUANTISATION}) and scored every model through the runtime with the BOP "
        f"metrics. Took {run.seconds / 60:.1f} min on {machine['cpu']} ({machine['cores']} cores)"
        f"{_step_path_text(example_metadata.training)}." + (f" {run.render_note}" if run.render_note else "")
        + f" {first_weights_text(_run_dirs(run))}",
        "\n".join(_code_lines(run)),
        "## Models\n\n" + "\n".join(model_lines)
        + f"\n\nModel card: [{run.link(model_card)}]({run.link(model_card)}). Try one with the runtime alone:\n\n"
        f"```bash\npopcode info {run.link(example)}\n"
        f"popcode predict {run.link(example)} {run.link(instance.image_path)} --box {box} "
        f"--obj-id {instance.obj_id}{camera} --top-k 2\n```",
        "## Accuracy (rotation from the model, translation from the ground truth: the paper's protocol)\n\n"
        f"Full tables, per object and per metric: [{run.link(eval_report)}]({run.link(eval_report)})\n\n"
        + _demote_headings(ambiguity_markdown({r.name: r.groups for r in run.results})),
        _targets_section(run),
        _look_alike_section(run),
        _demote_headings("\n\n".join(full_pose_markdown(run.results))),
        cluttered_markdown(run),
        _own_detector_section(run),
        _path_traced_section(run),
        _confidence_section(run),
        f"## Runtime latency (one thread, synthetic {BENCH_IMAGE_SHAPE[1]} x {BENCH_IMAGE_SHAPE[0]} scene)\n\n"
        + latency_markdown(run.latency),
        "## Figures\n\n" + "\n\n".join(figure_lines),
    ] if part) + "\n"


def _card_subject(run: DemoRun) -> str:
    """The model card's title: "the built-in objects" (as before) or the user's parts."""
    return "the built-in objects" if not run.objects_option else run.parts


def _code_lines(run: DemoRun) -> list[str]:
    """One line per object group: the code its models trained with, and why where it is not the size's."""
    if not run.code_notes:
        return []
    return ["Code per object group (one model each):", "", *(f"- {note}" for note in run.code_notes)]


def _scenes_text(size: PipelineSize) -> str:
    if not size.train_scenes:
        return ""
    return (f", and {size.train_scenes} cluttered bin scenes of them that make {100 * size.scene_share:g} % of "
            "every epoch's crops, each keeping its own clutter")


def _training_boxes_text(data: DataConfig) -> str:
    """Which boxes the training crops were cut from."""
    if data.box_noise == "none":
        return "crops of true boxes"
    noisy = f"crops of `{data.box_noise}` boxes (`data.box_noise`)"
    if data.box_noise_p == 1.0:
        return noisy
    return f"{noisy} for {100 * data.box_noise_p:g} % of them, true boxes for the rest"


def _step_path_text(training: dict[str, Any]) -> str:
    """How the training step ran (the same path for every model of one machine), as the report's sentence ends."""
    path = training.get("step_path")
    return "" if not path else f"; training step: {StepPath(**path).describe()}"


def _targets_section(run: DemoRun) -> str:
    by_name = {r.name: r for r in run.results}
    run_dirs = [path.parent for path in run.models.by_representation[POPCODE]]
    return targets_markdown(by_name[POPCODE], by_name.get(Representation.SINGLE_VARIABLE), run_dirs)


def _look_alike_section(run: DemoRun) -> str:
    clean = next(r for r in run.results if r.name == POPCODE)
    cluttered = next((r for r in run.cluttered.methods if r.name == POPCODE), None) if run.cluttered else None
    return look_alike_markdown(clean, cluttered)


def _run_dirs(run: DemoRun) -> list[Path]:
    return [path.parent for paths in run.models.by_representation.values() for path in paths]


def _epochs_text(run: DemoRun) -> str:
    """The epochs, and when they were fitted to a time budget, what they were fitted from."""
    epochs = f"{run.size.config.train.epochs} epochs"
    fit = run.epoch_fit
    if fit is None:
        return epochs
    return (f"{epochs}, fitted to a {fit.budget_s / 60:g}-minute budget on this machine: one epoch of every model "
            f"took {sum(fit.first_epoch_seconds.values()):.0f} s and the budget left {fit.seconds_left:.0f} s for "
            f"training, within {fit.bounds[0]}-{fit.bounds[1]} epochs")


def _percent(value: float) -> str:
    return "–" if np.isnan(value) else f"{100.0 * value:.1f}%"


def cluttered_markdown(run: DemoRun) -> str:
    """MSSD on the clean and the cluttered test split side by side, per visibility bin on the cluttered one, the
    best of the code's top-k hypotheses there, the cost of a detector's boxes, and the bin's targets."""
    if not run.cluttered:
        return ""
    clean = {r.name: r for r in run.results}
    methods, detector = run.cluttered.methods, run.cluttered.detector_boxes
    first = methods[0]
    bins = list(first.by_visibility)
    top_k = max((r.best_of_top_k.groups for r in methods if r.best_of_top_k is not None), key=len, default={})
    ks = [k for k in sorted(top_k) if k > 1]
    header = ["Method", "clean split", "cluttered split", *(f"best of top-{k}" for k in ks),
              *(f"visib {label} ({int(first.by_visibility[label]['instances'])})" for label in bins)]
    rows = [[r.name, _percent(clean[r.name].groups["All objects"]["MSSD"]), _percent(r.groups["All objects"]["MSSD"]),
             *(_percent(r.best_of_top_k.groups[k]["All objects"]) if r.best_of_top_k else "–" for k in ks),
             *(_percent(r.by_visibility[label]["MSSD"]) for label in bins)] for r in methods]
    if detector is not None:
        rows.append([f"{detector.name}, detector-like boxes", "–", _percent(detector.groups["All objects"]["MSSD"]),
                     *("–" for _ in ks), *(_percent(detector.by_visibility[label]["MSSD"]) for label in bins)])
    by_name = {r.name: r for r in methods}
    found = clutter_targets(by_name[POPCODE], by_name.get(Representation.SINGLE_VARIABLE), detector)
    instances = len(first.split.instances)
    report = run.out_dir / "eval_cluttered" / REPORT_MD
    parts = [
        "## The robot's bin: clean and cluttered test splits (MSSD, all objects)",
        f"The clean split shows one part alone; the cluttered one ({run.size.cluttered_test_scenes} scenes, "
        f"{instances} instances at least {100 * BOP19_MIN_VISIB_FRACT:g} % visible) drops several parts with repeats "
        "and distractors into a bin, seen from above with an industrial camera's noise, blur and exposure "
        "(`popcode-train render --scenes`), each crop cut from its ground-truth box (`bbox_obj`) as the paper does; "
        "the last row cuts the population code's crops from detector-like boxes instead (box-noise preset "
        "`detector`, IoU about 0.75 with the true box, clipped to the image). \"best of top-k\": the right pose "
        "among the code's k strongest distinct peaks (`--top-k`). Columns from visib: the cluttered split by "
        f"visible fraction (instances). Every table: [{run.link(report)}]({run.link(report)}).",
        markdown_table(header, rows),
        targets_table(found),
    ]
    if not all(t.met for t in found):
        parts.append(_clutter_limit_text(run, detector_missed=any(t.name == DETECTOR_TARGET and not t.met
                                                                  for t in found)))
    return "\n\n".join(parts)


def _clutter_limit_text(run: DemoRun, detector_missed: bool) -> str:
    """What limits a missed bin target, as measured on the validation splits."""
    text = ("What limits it: bench/results/scene-mix-quick.md measures MSSD on a cluttered validation split against "
            "the share of scene crops in training, and the bin's accuracy still rises with training compute "
            "(the quick budget trains a few epochs); `--size medium` or `--minutes M` buys more"
            + (f"; this run trained on {run.size.train_scenes} scenes." if run.size.train_scenes else "."))
    if not detector_missed:
        return text
    return (f"{text} What a detector's boxes cost grows with training; crops of detector-like boxes in training "
            "(`data.box_noise`, `data.box_noise_p`) halve it from about the medium budget on and cost the clean "
            f"split at the quick one (bench/results/box-noise-training.md); this run trained on "
            f"{_training_boxes_text(run.size.config.data)}.")


def _own_detector_section(run: DemoRun) -> str:
    """The run's own detector and the poses from its boxes, where the run trained one."""
    if run.cluttered is None or run.cluttered.own_detector is None:
        return ""
    own = run.cluttered.own_detector
    popcode = next(r for r in run.cluttered.methods if r.name == POPCODE)
    folder = run.out_dir / OWN_DETECTOR_FOLDER
    tables = folder / REPORT_MD if own.poses is not None else folder / DETECTIONS_FILE
    return own_detector_markdown(own, popcode, run.cluttered.detector_boxes, run.link(tables),
                                 run.step_seconds.get(DETECTOR_STAGE))


def _path_traced_section(run: DemoRun) -> str:
    if run.path_traced is None:
        return ""
    tables = run.out_dir / f"eval_{TRACED_FOLDER}" / REPORT_MD
    return path_traced_markdown(run.path_traced, run.link(tables))


def _confidence_section(run: DemoRun) -> str:
    """The confidence table and, when a model is calibrated, its reliability diagram."""
    reliability = run.out_dir / "eval" / RELIABILITY_PNG
    figure = f"\n\n![Reliability]({run.link(reliability)})" if reliability.is_file() else ""
    return _demote_headings(confidence_markdown(run.results)) + figure


def _cluttered_summary(cluttered: ClutteredResults | None) -> dict[str, Any]:
    if cluttered is None:
        return {}
    summary: dict[str, Any] = {
        r.name: {"groups": r.groups, "by_visibility": r.by_visibility,
                 "best_of_top_k": r.best_of_top_k.groups if r.best_of_top_k else None} for r in cluttered.methods}
    if cluttered.detector_boxes is not None:
        detector = cluttered.detector_boxes
        summary[f"{detector.name}, detector-like boxes"] = {"groups": detector.groups,
                                                           "by_visibility": detector.by_visibility}
    own = cluttered.own_detector
    if own is not None:
        summary["own detector"] = {"detection": own.detection.to_dict(), "mean_detect_ms": own.mean_detect_ms,
                                   "detector": str(own.detector)}
        if own.poses is not None:
            summary[own.poses.name] = {"groups": own.poses.groups, "by_visibility": own.poses.by_visibility}
    return summary


def write_outputs(run: DemoRun) -> dict[str, Any]:
    """Model card, samples, report and ``summary.json``; returns the summary."""
    model_card = write_model_card(run)
    samples = write_samples(run.split, run.out_dir / "samples")
    report = run.out_dir / REPORT_FILE
    write_bytes_atomic(report, report_markdown(run, model_card).encode())
    summary = {
        "size": run.size_name, "settings": asdict(run.size), "object_groups": run.groups,
        "objects": run.parts, "group_codes": list(run.code_notes),
        "epoch_fit": asdict(run.epoch_fit) if run.epoch_fit else None,
        "first_weights": first_weights(_run_dirs(run)),
        "wall_seconds": run.seconds, "machine": machine_description(), "step_seconds": run.step_seconds,
        "scores": {r.name: r.groups for r in run.results}, "latency": run.latency,
        "confidence": {r.name: r.confidence.to_dict() for r in run.results if r.confidence is not None},
        "cluttered_scores": _cluttered_summary(run.cluttered),
        "path_traced_scores": path_traced_summary(run.path_traced),
        "models": {name: [str(p) for p in paths] for name, paths in run.models.by_representation.items()},
        "quantised_models": [str(p) for p in run.models.quantised],
        "figures": {title: [str(p) for p in paths] for title, paths in run.figures.items()},
        "report": str(report), "model_card": str(model_card), "samples": str(samples),
    }
    write_bytes_atomic(run.out_dir / SUMMARY_FILE, (to_json(summary) + "\n").encode())
    return summary
