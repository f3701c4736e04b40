"""The end-to-end demo: render the built-in objects (or the parts of a user's BOP models folder, checked first:
:mod:`popcode_trainer.demo.parts`), train the population code and the single-variable baseline the same way,
one model per object group (:func:`~popcode_trainer.demo.steps.object_groups`, each on the code
:mod:`popcode_trainer.demo.group_codes` chooses; a user's group whose parts need different codes is split into
one group per code), export (float and quantised), evaluate with the BOP metrics,
time the runtime, draw the figures and write one report, all under one run folder.

Every step resumes (see :mod:`popcode_trainer.demo.steps`), so rerunning an
interrupted demo with the same folder continues where it stopped.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.output_lock import OutputLock
from popcode_runtime.depth.icp import INSTALL_HINT, require_small_gicp
from popcode_runtime.inference.benchmark import benchmark_estimator
from popcode_runtime.inference.estimator import PoseEstimator

from ..data.bop import model_path
from ..data.box_noise import box_noise_preset
from ..data.render import BUILTIN_MODELS_FOLDER
from ..eval.pipeline.detector_boxes import with_detector_boxes
from ..eval.pipeline.evaluate import MethodResult, evaluate_models
from ..eval.pipeline.instance_code import instance_code
from ..eval.pipeline.models import Method, load_model
from ..eval.pipeline.sensitivity import sensitivity_curves
from ..eval.pipeline.split import EvalSplit, read_eval_split
from ..eval.reporting.figures import plot_instance_code, plot_sensitivity
from ..eval.reporting.overview_figures import metrics_files_of, plot_crop_grid, plot_training_curves
from ..eval.reporting.report import write_report
from ..export.model_io import read_onnx_metadata
from ..train.config import CodeConfig
from ..train.pretrained import resolve_start
from ..train.schedule import first_epoch_rate_is_fixed
from . import epoch_budget
from .detector_step import DETECTOR_STAGE, OWN_DETECTOR_FOLDER, score_own_detector, train_demo_detector
from .group_codes import GroupCode, choose_group_codes
from .parts import BUILTIN, Parts, load_parts
from .path_traced_step import score_path_traced
from .plan import FIRST_EPOCHS, PATH_TRACED_STAGE, SECONDS_PER_EXPORT, StagePlan, minutes_text, plan, train_stage
from .report import POPCODE, QUANTISATION, ClutteredResults, DemoRun, TrainedModels, write_outputs
from .sizes import BASELINE, DEMO_SIZES, HIDDEN_SIZES, DemoSize
from .steps import (
    TEST_SEED_OFFSET,
    PipelineSize,
    object_groups,
    render_splits,
    run_dir,
    train_and_export,
    train_first_epoch,
)

CLUTTERED_SEED_OFFSET = 2000  # training renders use the seed, the clean test split seed + 1000
LATENCY_BATCHES = (1, 8)
CLUTTERED_METHODS = (POPCODE, BASELINE)  # scored on the cluttered split too, side by side with the clean one
CLUTTERED_TOP_K = 3  # the population code's best of its top-k hypotheses in clutter
DETECTOR_BOXES = "detector"  # the box-noise preset the cluttered split is scored with once more (IoU about 0.75)
DEMO_LOCK = "demo.lock"  # held in the run folder while a demo writes it; each model's training holds its own


def run_demo(size_name: str, out_dir: str | Path, size: PipelineSize | None = None,
             latency_iterations: int = 50, minutes: float | None = None,
             objects: str | Path = BUILTIN) -> dict[str, Any]:
    """Run every step into ``out_dir``; returns the summary (also written as ``summary.json``).

    Without ``size`` the named size is used with its time budget; ``minutes`` sets a budget for any size
    (the epochs are then fitted to it, within the named size's bounds). ``objects``: ``"builtin"`` or a BOP
    models folder, checked before anything is written. A second demo into ``out_dir`` is refused while this one
    runs (it holds :data:`DEMO_LOCK`).
    """
    sizes = {**DEMO_SIZES, **HIDDEN_SIZES}
    if size_name not in sizes and size is None:
        raise PopcodeError(f"unknown demo size {size_name!r}; choose from {list(DEMO_SIZES)}")
    demo = sizes.get(size_name, DemoSize(size, "a custom size"))
    if minutes is None and size is None:
        minutes = demo.minutes
    demo = replace(demo, minutes=minutes)
    size = size or demo.pipeline
    if POPCODE not in size.representations:
        raise PopcodeError("the demo needs the population code among its representations")
    started = time.perf_counter()
    if str(objects) != BUILTIN:
        print(f"checking the parts of {objects} and choosing each group's code", flush=True)
    parts, codes = prepare_parts(objects, size.config.code)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with OutputLock(out_dir / DEMO_LOCK, f"another popcode-train demo is writing {out_dir} (it holds {DEMO_LOCK}); "
                                        "wait for it to end, or give another --out"):
        groups = [list(group.obj_ids) for group in codes]
        objects_count = len(parts.obj_ids)
        stages = plan(size, groups, objects_count, fit_epochs=minutes is not None)
        duration = (f"the epochs fitted so that it takes about {minutes:g} min on this machine" if minutes is not None
                    else f"{size.config.train.epochs} epochs, about {minutes_text(stages.remaining_s())} on a 2-core "
                         "CPU (the estimate corrects itself as steps finish)")
        print(f"popcode demo, size {size_name}: {len(stages.estimates)} steps, {duration}; output in {out_dir}",
              flush=True)
        if not parts.builtin:
            print(f"Checked {describe_parts(parts, codes)}", flush=True)
        with stages.stage("render"):
            train_split, test_split = render_splits(size, out_dir, parts=parts)
        detector = None
        if size.detector_seconds:
            with stages.stage(DETECTOR_STAGE):
                detector = train_demo_detector(size, train_split, out_dir, parts.obj_ids)
        epoch_fit = None
        if minutes is not None:
            with stages.stage(FIRST_EPOCHS):
                epoch_fit = fit_epochs(size, demo, codes, train_split, out_dir, started, stages)
            size = size.with_epochs(epoch_fit.epochs)
            # What is left of each model's training is now measured, not estimated: stated in reference seconds.
            stages.revise({train_stage(r, g): (epoch_fit.epochs - 1) * epoch_fit.first_epoch_seconds[
                run_dir(out_dir, r, g).name] / stages.scale + SECONDS_PER_EXPORT for r in size.representations
                for g in groups})
            print(f"{epoch_fit.epochs} epochs: one epoch of every model takes "
                  f"{sum(epoch_fit.first_epoch_seconds.values()):.0f} s here and the {minutes:g}-minute budget left "
                  f"{epoch_fit.seconds_left:.0f} s for training (bounds {epoch_fit.bounds[0]}-{epoch_fit.bounds[1]})",
                  flush=True)
        models = train_models(size, codes, train_split, out_dir, stages)
        with stages.stage("evaluate"):
            split, results = evaluate_clean(demo_methods(models), test_split)
            write_report(results, out_dir / "eval")
        cluttered = None
        if size.cluttered_test_scenes:
            with stages.stage("cluttered test split"):
                cluttered = evaluate_cluttered(size, models, out_dir, parts, detector)
        path_traced = None
        if size.path_traced_images:
            with stages.stage(PATH_TRACED_STAGE):
                path_traced = score_path_traced([m for m in demo_methods(models) if m.name == POPCODE], parts,
                                                size.path_traced_images, size.config.train.seed + TEST_SEED_OFFSET,
                                                out_dir)
        with stages.stage("latency"):
            latency = measure_latency(models, latency_iterations)
        with stages.stage("figures"):
            run_dirs = [run_dir(out_dir, r, g) for r in size.representations for g in groups]
            figures = draw_figures(results, split, models, run_dirs, out_dir / "figures")
        run = DemoRun(size_name, size, groups, out_dir, models, split, results, latency, figures, dict(stages.done),
                      cluttered, epoch_fit, parts.describe(), parts.objects_option(), tuple(g.note for g in codes),
                      parts.fill_range()[1], path_traced)
        summary = write_outputs(run)
        print(f"\ndone in {minutes_text(time.perf_counter() - started)}; report: {summary['report']}", flush=True)
        return summary


def fit_epochs(size: PipelineSize, demo: DemoSize, codes: Sequence[GroupCode], train_split: Path,
               out_dir: Path, started: float, stages: StagePlan) -> epoch_budget.EpochFit:
    """Train every model's first epoch and choose the epochs that fill ``demo.minutes`` counted from ``started``
    (see :mod:`popcode_trainer.demo.epoch_budget`); an interrupted run's earlier fit is kept."""
    earlier = epoch_budget.load(out_dir)
    names = {run_dir(out_dir, r, g.obj_ids).name for r in size.representations for g in codes}
    if earlier is not None and set(earlier.first_epoch_seconds) == names:
        return earlier
    if earlier is not None:  # started by a version that grouped the parts otherwise
        raise PopcodeError(f"{out_dir} was started with other models ({', '.join(sorted(earlier.first_epoch_seconds))}"
                           f"; now {', '.join(sorted(names))}): use another --out, or delete it to start over")
    bounds = epoch_bounds(demo, size)
    if not first_epoch_rate_is_fixed(size.config.train.schedule, bounds[0]):
        raise PopcodeError(f"fitting the epochs to a time budget needs a schedule whose first epoch does not depend "
                           f"on the run's length (constant, anneal), not {size.config.train.schedule!r}: pass --epochs")
    first = {}
    for representation in size.representations:
        for group in codes:
            seconds = train_first_epoch(size, representation, group.obj_ids, train_split, out_dir, group.code)
            first[run_dir(out_dir, representation, group.obj_ids).name] = seconds
    elapsed_s = time.perf_counter() - started
    training = [train_stage(r, g.obj_ids) for r in size.representations for g in codes]
    exports = stages.scale * SECONDS_PER_EXPORT * len(training)
    other_steps = stages.remaining_s(after=[FIRST_EPOCHS, *training]) + exports
    result = epoch_budget.fit(first, 60.0 * demo.minutes, 60.0 * demo.minutes - elapsed_s - other_steps, bounds)
    epoch_budget.save(result, out_dir)
    return result


def epoch_bounds(demo: DemoSize, size: PipelineSize) -> tuple[int, int]:
    """The bounds of the fitted epochs: the size's, or its fine-tune bounds where the models take a pretrained
    start (``train.init``, :mod:`popcode_trainer.train.pretrained`)."""
    if demo.fine_tune_epoch_bounds is None:
        return demo.epoch_bounds
    start, _ = resolve_start(size.config.train.init, replace(size.config.network,
                                                             input_size=size.config.data.crop_size))
    return demo.epoch_bounds if start is None else demo.fine_tune_epoch_bounds


def train_models(size: PipelineSize, codes: Sequence[GroupCode], train_split: Path, out_dir: Path,
                 stages: StagePlan) -> TrainedModels:
    by_representation: dict[str, list[Path]] = {}
    quantised = []
    for representation in size.representations:
        for group in codes:
            kinds = (QUANTISATION,) if representation == POPCODE else ()
            with stages.stage(train_stage(representation, group.obj_ids)):
                path, _ = train_and_export(size, representation, group.obj_ids, train_split, out_dir, kinds,
                                           group.code)
            by_representation.setdefault(representation, []).append(path)
            quantised += [path.with_name(f"{path.stem}.{kind}.onnx") for kind in kinds]
    return TrainedModels(by_representation, quantised)


def demo_methods(models: TrainedModels) -> list[Method]:
    """The table rows: the population code (argmax, refined, quantised) and the baseline."""
    popcode = models.by_representation[POPCODE]
    methods = [Method(POPCODE, tuple(load_model(p) for p in popcode)),
               Method(f"{POPCODE} (refined)", tuple(load_model(p, decoder="refined") for p in popcode)),
               Method(f"{POPCODE} ({QUANTISATION})", tuple(load_model(p) for p in models.quantised))]
    methods += [Method(name, tuple(load_model(p) for p in paths))
                for name, paths in models.by_representation.items() if name != POPCODE]
    return methods


def can_refine() -> bool:
    """Whether refinement against depth can run: its library is the runtime's optional extra (make demo installs it)."""
    try:
        require_small_gicp()
    except PopcodeError:
        return False
    return True


def evaluate_clean(methods: Sequence[Method], test_split: Path) -> tuple[EvalSplit, list[MethodResult]]:
    """Every method on the clean test split, with full 6-D poses from the box and, for the population code, from
    the depth images (and refined against them where small_gicp is installed)."""
    split = read_eval_split([test_split], test_split / BUILTIN_MODELS_FOLDER)
    refine = can_refine()
    if not refine:
        print(f"small_gicp is not installed: the depth rows skip refinement ({INSTALL_HINT})", flush=True)
    return split, evaluate_models(methods, split, translation=True, depth=True, refine=refine,
                                  depth_methods={POPCODE})


def evaluate_cluttered(size: PipelineSize, models: TrainedModels, out_dir: Path, parts: Parts,
                       detector_path: Path | None = None) -> ClutteredResults:
    """The population code and the baseline on a cluttered split (rendered once, fixed seed): rotation metrics
    without the depth-based ones, scored per visibility bin, with the code's best of its top-k hypotheses; then
    the population code again with detector-like boxes (:data:`DETECTOR_BOXES`) and, given the run's
    ``detector_path``, from that detector's boxes alone."""
    split_dir = parts.render_scenes(out_dir / "test_cluttered", size.cluttered_test_scenes,
                                    size.config.train.seed + CLUTTERED_SEED_OFFSET, progress=True)
    split = read_eval_split([split_dir], split_dir / BUILTIN_MODELS_FOLDER)
    methods = [m for m in demo_methods(models) if m.name in CLUTTERED_METHODS]
    results = evaluate_models(methods, split, vsd=False, top_k=CLUTTERED_TOP_K)
    write_report(results, out_dir / "eval_cluttered")
    noisy = with_detector_boxes(split, box_noise_preset(DETECTOR_BOXES), seed=size.config.train.seed)
    detector = evaluate_models([m for m in methods if m.name == POPCODE], noisy, vsd=False)
    write_report(detector, out_dir / "eval_cluttered_detector_boxes")
    own = None
    if detector_path is not None:
        own = score_own_detector(detector_path, models.by_representation[POPCODE], split_dir, split, out_dir,
                                 f"{POPCODE}, own detector")
        if own.poses is not None:
            write_report([own.poses], out_dir / OWN_DETECTOR_FOLDER)
    return ClutteredResults(results, detector[0], own)


def measure_latency(models: TrainedModels, iterations: int) -> list[dict[str, Any]]:
    """Batch-1 and batch-8 latency of every exported model of the largest group, one thread."""
    largest = int(np.argmax([len(read_onnx_metadata(p).objects) for p in models.by_representation[POPCODE]]))
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


def draw_figures(results: Sequence[MethodResult], split: EvalSplit, models: TrainedModels, run_dirs: Sequence[Path],
                 out_dir: Path) -> dict[str, list[Path]]:
    """Training curves, metric sensitivity, code on the sphere and a grid of crops with their poses."""
    from ..data.gl import DepthRenderer
    from ..data.meshes import load_mesh
    from ..eval.pipeline.instance_errors import ObjectModel

    out_dir.mkdir(parents=True, exist_ok=True)
    figures = {"training curves": [plot_training_curves(metrics_files_of(run_dirs), out_dir / "training.png")],
               "test crops": [plot_crop_grid(result, out_dir / f"crops_{i}.png") for i, result in enumerate(results)
                              if result.name in (POPCODE, BASELINE)]}
    codes = []
    for path in models.by_representation[POPCODE]:
        estimator = PoseEstimator(path)
        instance = next(inst for inst in split.instances if inst.obj_id in estimator.metadata.objects)
        codes.append(plot_instance_code(instance_code(estimator, instance), out_dir / f"code_obj{instance.obj_id}.png"))
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


def prepare_parts(objects: str | Path, code: CodeConfig) -> tuple[Parts, list[GroupCode]]:
    """The parts checked (:mod:`~popcode_trainer.demo.parts`), grouped, and each group's code chosen: every check
    that comes before the long work. A user's parts may get a finer grid than ``code``'s (and a group of their own
    where they need another code than the rest); the built-in ones keep the size's grid and groups."""
    parts = load_parts(objects)
    groups = object_groups(parts.models_info)
    return parts, choose_group_codes(code, parts.models_info, groups, finer=not parts.builtin)


def describe_parts(parts: Parts, codes: Sequence[GroupCode]) -> str:
    """What the run will train: the parts, how they are framed where that differs from the renderer's default,
    and per object group (one model each) its code."""
    render_note = parts.fill_range()[1]
    return "\n".join([f"{parts.describe()}; one model per object group:", *(f"- {g.note}" for g in codes),
                      *([render_note] if render_note else [])])
