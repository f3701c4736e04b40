"""The end-to-end demo: render the built-in objects, train the population code and the single-variable
baseline the same way, export (float and quantised), evaluate with the BOP metrics, time the runtime,
draw the figures and write one report, all under one run folder.

Every step resumes (see :mod:`popcode_trainer.pipeline`), so rerunning an
interrupted demo with the same folder continues where it stopped.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.benchmark import benchmark_estimator, machine_description
from popcode_runtime.errors import PopcodeError
from popcode_runtime.estimator import PoseEstimator
from popcode_runtime.metadata import Representation

from .data.bop import model_path
from .data.objects import BUILTIN_PARTS
from .data.render import BUILTIN_MODELS_FOLDER
from .eval.evaluate import EvalSplit, Method, MethodResult, OnnxModel, evaluate_models, read_eval_split
from .eval.figures import plot_instance_code, plot_sensitivity, sensitivity_curves
from .eval.overview_figures import metrics_files_of, plot_crop_grid, plot_training_curves
from .eval.report import REPORT_MD, write_report
from .eval.tables import methods_markdown, to_json
from .pipeline import SMALL_NETWORK, PipelineSize, object_groups, render_splits, run_dir, train_and_export

POPCODE, BASELINE = Representation.POPULATION_CODE, Representation.SINGLE_VARIABLE
QUANTISATION = "int8"
REPORT_FILE = "report.md"
SUMMARY_FILE = "summary.json"
LATENCY_BATCHES = (1, 8)


@dataclass(frozen=True)
class DemoSize:
    """A demo budget and what it is for."""

    pipeline: PipelineSize
    purpose: str


DEMO_SIZES = {
    "quick": DemoSize(PipelineSize(train_images_per_object=400, test_images_per_object=40, epochs=12, n_axes=642,
                                   n_angles=36, network=SMALL_NETWORK, representations=(POPCODE, BASELINE)),
                      "about 15 minutes on a 2-core CPU"),
    "medium": DemoSize(PipelineSize(train_images_per_object=2000, test_images_per_object=100, epochs=30, n_axes=642,
                                    n_angles=36, network=SMALL_NETWORK, representations=(POPCODE, BASELINE)),
                       "a few hours on a 2-core CPU, minutes on a GPU"),
    "paper": DemoSize(PipelineSize(train_images_per_object=8000, test_images_per_object=200, epochs=80, n_axes=2562,
                                   n_angles=36, network={}, batch_size=64, lr=2e-4, num_workers=8,
                                   representations=(POPCODE, BASELINE)),
                      "the paper's code, network and schedule; for a GPU"),
}

# Seconds per unit on the 2-core CPU this project is developed on (small network, 642 x 36 code); the
# plan rescales its estimate by how long the finished steps really took, so other machines converge.
SECONDS_PER_RENDERED_IMAGE = 0.02
SECONDS_PER_TRAINING_SAMPLE = 0.0045
SECONDS_PER_EVALUATED_INSTANCE = 0.15
SECONDS_LATENCY = 40.0
SECONDS_FIGURES = 30.0


class StagePlan:
    """Named steps with estimated seconds; announces each with the time left overall.

    The estimate of what is left is scaled by (time taken / time estimated) of
    the finished steps, so a faster or slower machine corrects it as it goes.
    """

    def __init__(self, stages: Sequence[tuple[str, float]]) -> None:
        self.estimates = dict(stages)
        self.done: dict[str, float] = {}

    def remaining_s(self, after: Sequence[str] = ()) -> float:
        estimated_done = sum(self.estimates[name] for name in self.done)
        scale = sum(self.done.values()) / estimated_done if estimated_done > 0 else 1.0
        left = [name for name in self.estimates if name not in self.done and name not in after]
        return scale * sum(self.estimates[name] for name in left)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        index = list(self.estimates).index(name) + 1
        this_step = self.remaining_s() - self.remaining_s([name])
        print(f"\n[{index}/{len(self.estimates)}] {name}: about {_minutes(this_step)}; "
              f"about {_minutes(self.remaining_s())} left overall", flush=True)
        started = time.perf_counter()
        yield
        self.done[name] = time.perf_counter() - started


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def plan(size: PipelineSize, groups: Sequence[Sequence[int]], objects: int) -> StagePlan:
    """The demo's steps with their estimated seconds on the reference CPU."""
    images = objects * (size.train_images_per_object + size.test_images_per_object)
    width = np.prod(size.network.get("conv_channels", [128, 256, 256])) / np.prod(SMALL_NETWORK["conv_channels"])
    stages = [("render", images * SECONDS_PER_RENDERED_IMAGE)]
    for representation in size.representations:
        for obj_ids in groups:
            samples = len(obj_ids) * size.train_images_per_object * size.epochs
            stages.append((_train_stage(representation, obj_ids),
                           samples * SECONDS_PER_TRAINING_SAMPLE * max(1.0, width ** (1 / 3))))
    methods = len(size.representations) + 2  # + refined decoder + quantised model
    stages += [("evaluate", methods * objects * size.test_images_per_object * SECONDS_PER_EVALUATED_INSTANCE),
               ("latency", SECONDS_LATENCY), ("figures", SECONDS_FIGURES)]
    return StagePlan(stages)


def _train_stage(representation: str, obj_ids: Sequence[int]) -> str:
    return f"train {representation} for objects {', '.join(map(str, obj_ids))}"


@dataclass(frozen=True)
class TrainedModels:
    """ONNX files per representation (one per object group) and the population code's quantised ones."""

    by_representation: dict[str, list[Path]]
    quantised: list[Path]


def train_models(size: PipelineSize, groups: Sequence[Sequence[int]], train_split: Path, out_dir: Path,
                 stages: StagePlan) -> TrainedModels:
    by_representation: dict[str, list[Path]] = {}
    quantised = []
    for representation in size.representations:
        for obj_ids in groups:
            kinds = (QUANTISATION,) if representation == POPCODE else ()
            with stages.stage(_train_stage(representation, obj_ids)):
                path, _ = train_and_export(size, representation, obj_ids, train_split, out_dir, kinds)
            by_representation.setdefault(representation, []).append(path)
            quantised += [path.with_name(f"{path.stem}.{kind}.onnx") for kind in kinds]
    return TrainedModels(by_representation, quantised)


def demo_methods(models: TrainedModels) -> list[Method]:
    """The table rows: the population code (argmax, refined, quantised) and the baseline."""
    popcode = models.by_representation[POPCODE]
    methods = [Method(POPCODE, tuple(OnnxModel(p) for p in popcode)),
               Method(f"{POPCODE} (refined)", tuple(OnnxModel(p, decoder="refined") for p in popcode)),
               Method(f"{POPCODE} ({QUANTISATION})", tuple(OnnxModel(p) for p in models.quantised))]
    methods += [Method(name, tuple(OnnxModel(p) for p in paths))
                for name, paths in models.by_representation.items() if name != POPCODE]
    return methods


def measure_latency(models: TrainedModels, iterations: int) -> list[dict[str, Any]]:
    """Batch-1 and batch-8 latency of every exported model of the largest group, one thread."""
    largest = int(np.argmax([len(PoseEstimator(p).metadata.objects) for p in models.by_representation[POPCODE]]))
    chosen = {f"{POPCODE} (fp32)": models.by_representation[POPCODE][largest],
              f"{POPCODE} ({QUANTISATION})": models.quantised[largest]}
    chosen |= {f"{name} (fp32)": paths[largest] for name, paths in models.by_representation.items()
               if name != POPCODE}
    records = []
    for name, path in chosen.items():
        estimator = PoseEstimator(path, threads=1)
        for stats in benchmark_estimator(estimator, LATENCY_BATCHES, warmup=max(2, iterations // 10),
                                         iterations=iterations, threads=1):
            records.append({"model": name, "file": str(path), "megabytes": path.stat().st_size / 1e6,
                            **stats.to_dict()})
    return records


def latency_markdown(records: Sequence[dict[str, Any]]) -> str:
    lines = ["| model | MB | batch | stage | median ms | p90 ms | crops/s |", "|---|---|---|---|---|---|---|"]
    for r in records:
        lines.append(f"| {r['model']} | {r['megabytes']:.1f} | {r['batch']} | {r['stage']} | {r['median_ms']:.2f} | "
                     f"{r['p90_ms']:.2f} | {1000 * r['batch'] / r['median_ms']:.0f} |")
    return "\n".join(lines)


def draw_figures(results: Sequence[MethodResult], split: EvalSplit, models: TrainedModels, run_dirs: Sequence[Path],
                 out_dir: Path) -> dict[str, list[Path]]:
    """Training curves, metric sensitivity, code on the sphere and a grid of crops with their poses."""
    from .data.render import DepthRenderer, load_mesh
    from .eval.instance_errors import ObjectModel

    out_dir.mkdir(parents=True, exist_ok=True)
    figures = {"training curves": [plot_training_curves(metrics_files_of(run_dirs), out_dir / "training.png")],
               "test crops": [plot_crop_grid(result, out_dir / f"crops_{i}.png") for i, result in enumerate(results)
                              if result.name in (POPCODE, BASELINE)]}
    codes = []
    for path in models.by_representation[POPCODE]:
        estimator = PoseEstimator(path)
        instance = next(inst for inst in split.instances if inst.obj_id in estimator.metadata.objects)
        codes.append(plot_instance_code(estimator, instance, out_dir / f"code_obj{instance.obj_id}.png"))
    figures["code on the sphere"] = codes
    # Metric sensitivity (paper Fig. 4) on the first test instance of the object with the most symmetries.
    obj_id = max(split.obj_ids, key=lambda o: len(split.models_info[o].get("symmetries_discrete", [])))
    instance = next(inst for inst in split.instances if inst.obj_id == obj_id)
    mesh = load_mesh(model_path(split.models_dir, obj_id))
    obj = ObjectModel.from_info(np.asarray(mesh.vertices), split.models_info[obj_id])
    width, height = (int(v) for v in 2 * instance.K[:2, 2])
    renderer = DepthRenderer(mesh.vertices, mesh.faces, width, height)
    try:
        curves = sensitivity_curves(obj.pts_mm, obj.syms, obj.diameter_mm, instance.K, instance.R_m2c,
                                    instance.t_m2c_mm, np.linspace(0.0, 180.0, 37), np.random.default_rng(0),
                                    render_depth=lambda R, t: renderer.render(instance.K, R, t))
    finally:
        renderer.close()
    figures["metric sensitivity"] = [plot_sensitivity(curves, out_dir / "sensitivity.png",
                                                      f"Metric sensitivity, object {obj_id}")]
    return figures


def write_model_card(models: TrainedModels, results: Sequence[MethodResult], latency: Sequence[dict[str, Any]],
                     size_name: str, size: PipelineSize, out_dir: Path) -> Path:
    """What a user of the population-code models needs: objects, symmetry, data, accuracy, speed, how to rebuild."""
    by_name = {r.name: r for r in results}
    lines = [f"# Model card: population-code models of the built-in objects (demo size `{size_name}`)", ""]
    for path, quantised in zip(models.by_representation[POPCODE], models.quantised, strict=True):
        meta = PoseEstimator(path).metadata
        objects = ", ".join(f"{o} ({_symmetry_name(meta.objects[o])})" for o in sorted(meta.objects))
        layout = meta.code
        lines.append(f"- `{path.name}` in `{path.parent.name}/`: objects {objects}; code "
                     f"{layout.n_axes} axes" + ("" if layout.axis_only else f" x {layout.n_angles} angles")
                     + f", sigma {layout.sigma_deg:.0f} deg; {meta.rotation_frame} rotation; "
                     f"{path.stat().st_size / 1e6:.1f} MB ({QUANTISATION}: {quantised.stat().st_size / 1e6:.1f} MB)")
    lines += [
        "",
        "## Training",
        f"Rendered grey 128 x 128 images of the six built-in parts (random rotation, position and lighting; "
        f"`popcode_trainer.data.render`), {size.train_images_per_object} per object, the paper's augmentation; "
        f"{size.epochs} epochs, batch {size.batch_size}, Adam lr {size.lr}; network {size.network or 'paper size'}.",
        "",
        "## Accuracy (separate rendered test split; rotation from the model, translation from the ground truth)",
        methods_markdown({name: r.groups["All objects"] for name, r in by_name.items()}),
        "",
        "## Latency (one thread)",
        latency_markdown(latency),
        "",
        f"Measured on: {machine_description()['cpu']}.",
        "",
        "## Reproduce",
        f"`popcode-train demo --size {size_name} --out DIR`; the models are `DIR/runs/population_code_*/model*.onnx`.",
    ]
    path = out_dir / "model_card.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _symmetry_name(info: dict[str, Any]) -> str:
    if info.get("symmetries_continuous"):
        return "continuous" + (" + flip" if info.get("symmetries_discrete") else "")
    count = len(info.get("symmetries_discrete", []))
    return "no symmetry" if count == 0 else f"{count + 1} symmetric poses"


def _demote_headings(markdown: str) -> str:
    return "\n".join("#" + line if line.startswith("#") else line for line in markdown.splitlines())


def report_markdown(size_name: str, size: PipelineSize, groups: Sequence[Sequence[int]], seconds: float,
                    split: EvalSplit, eval_dir: Path, latency: Sequence[dict[str, Any]], figures: dict[str, list[Path]],
                    model_card: Path, models: TrainedModels, out_dir: Path) -> str:
    """The run's one-page report, with links relative to the run folder."""
    def link(path: Path) -> str:
        return os.path.relpath(path, out_dir)

    machine = machine_description()
    model_lines = [f"- {name}: " + ", ".join(f"[`{link(p)}`]({link(p)})" for p in paths)
                   for name, paths in models.by_representation.items()]
    model_lines.append(f"- {POPCODE} ({QUANTISATION}): "
                       + ", ".join(f"[`{link(p)}`]({link(p)})" for p in models.quantised))
    figure_lines = [f"### {title}\n\n" + "\n".join(f"![{title}]({link(p)})" for p in paths)
                    for title, paths in figures.items()]
    example = models.by_representation[POPCODE][-1]
    example_objects = PoseEstimator(example).metadata.objects
    instance = next(inst for inst in split.instances if inst.obj_id in example_objects)
    box = ",".join(f"{v:g}" for v in instance.box)
    return "\n\n".join([
        f"# popcode demo (`--size {size_name}`)",
        f"Rendered the six built-in parts ({size.train_images_per_object} training and "
        f"{size.test_images_per_object} test images per object), trained {', '.join(size.representations)} "
        f"with the same network, data and budget ({size.epochs} epochs; objects pooled as {list(groups)}), "
        f"exported ONNX (float and {QUANTISATION}) and scored every model through the runtime with the BOP "
        f"metrics. Took {seconds / 60:.1f} min on {machine['cpu']} ({machine['cores']} cores).",
        "## Models\n\n" + "\n".join(model_lines) + f"\n\nModel card: [{link(model_card)}]({link(model_card)}). "
        f"Try one with the runtime alone:\n\n```bash\npopcode info {link(example)}\n"
        f"popcode predict {link(example)} {link(instance.image_path)} --box {box} --top-k 2\n```",
        "## Accuracy\n\nFull tables: [" + link(eval_dir / REPORT_MD) + "](" + link(eval_dir / REPORT_MD) + ")\n\n"
        + _demote_headings((eval_dir / REPORT_MD).read_text().split("## Scores per object")[0].strip()),
        "## Runtime latency (one thread, synthetic 720 x 540 scene)\n\n" + latency_markdown(latency),
        "## Figures\n\n" + "\n\n".join(figure_lines),
    ]) + "\n"


def run_demo(size_name: str, out_dir: str | Path, size: PipelineSize | None = None,
             latency_iterations: int = 50) -> dict[str, Any]:
    """Run every step into ``out_dir``; returns the summary (also written as ``summary.json``)."""
    if size_name not in DEMO_SIZES and size is None:
        raise PopcodeError(f"unknown demo size {size_name!r}; choose from {list(DEMO_SIZES)}")
    size = size or DEMO_SIZES[size_name].pipeline
    if POPCODE not in size.representations:
        raise PopcodeError("the demo needs the population code among its representations")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    groups = object_groups({part.obj_id: part.symmetries for part in BUILTIN_PARTS})
    stages = plan(size, groups, sum(map(len, groups)))
    print(f"popcode demo, size {size_name}: {len(stages.estimates)} steps, about "
          f"{_minutes(stages.remaining_s())} on a 2-core CPU (the estimate corrects itself as steps finish); "
          f"output in {out_dir}", flush=True)
    with stages.stage("render"):
        train_split, test_split = render_splits(size, out_dir)
    models = train_models(size, groups, train_split, out_dir, stages)
    with stages.stage("evaluate"):
        split = read_eval_split([test_split], test_split / BUILTIN_MODELS_FOLDER)
        results = evaluate_models(demo_methods(models), split)
        write_report(results, out_dir / "eval")
    with stages.stage("latency"):
        latency = measure_latency(models, latency_iterations)
    with stages.stage("figures"):
        run_dirs = [run_dir(out_dir, r, g) for r in size.representations for g in groups]
        figures = draw_figures(results, split, models, run_dirs, out_dir / "figures")
        model_card = write_model_card(models, results, latency, size_name, size, out_dir)
    seconds = time.perf_counter() - started
    report = out_dir / REPORT_FILE
    report.write_text(report_markdown(size_name, size, groups, seconds, split, out_dir / "eval", latency, figures,
                                      model_card, models, out_dir))
    summary = {
        "size": size_name, "settings": asdict(size), "object_groups": groups, "wall_seconds": seconds,
        "machine": machine_description(), "step_seconds": stages.done,
        "scores": {r.name: r.groups for r in results}, "latency": list(latency),
        "models": {name: [str(p) for p in paths] for name, paths in models.by_representation.items()},
        "quantised_models": [str(p) for p in models.quantised],
        "figures": {title: [str(p) for p in paths] for title, paths in figures.items()},
        "report": str(report), "model_card": str(model_card),
    }
    (out_dir / SUMMARY_FILE).write_text(to_json(summary) + "\n")
    print(f"\ndone in {_minutes(seconds)}; report: {report}", flush=True)
    return summary
