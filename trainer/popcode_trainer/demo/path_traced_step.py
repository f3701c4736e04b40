"""What to expect on a real camera: the first images of the demo's clean test split path traced (physically based
metals, plastics and lights) and scored beside the same images as the rasteriser drew them.

The models never saw a path-traced image, so the drop between the two is what the rasteriser's look costs
them (for the shipped models, on larger validation splits: bench/results/path-traced.md). Without the
optional Mitsuba extra the step says what to install and the report says it was skipped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from popcode_runtime.base.errors import PopcodeError

from ..data.path_trace import PathTraceSettings, import_mitsuba
from ..data.path_traced_split import path_trace_split
from ..data.render import BUILTIN_MODELS_FOLDER
from ..eval.pipeline.evaluate import MethodResult, evaluate_models
from ..eval.pipeline.models import Method
from ..eval.pipeline.split import read_eval_split
from ..eval.reporting.report import write_report
from ..metrics.paired import PairedDifference, instance_mssd_scores, paired_difference
from .parts import Parts

RENDERED_FOLDER, TRACED_FOLDER = "test_for_tracing", "test_path_traced"


@dataclass(frozen=True)
class PathTracedResults:
    """The population code on the rendered and the path-traced images (None where the step was skipped)."""

    images: int
    rendered: MethodResult | None = None
    path_traced: MethodResult | None = None
    mssd: PairedDifference | None = None  # path traced against rendered, instance by instance
    skipped: str = ""  # why, when it was


def score_path_traced(methods: Sequence[Method], parts: Parts, images_per_object: int, seed: int,
                      out_dir: Path) -> PathTracedResults:
    """Render the first ``images_per_object`` test images of every part (``seed``: the clean test split's), path
    trace them and score ``methods`` on both."""
    try:
        import_mitsuba()
    except PopcodeError as error:
        print(f"skipping the path-traced test images: {error}", flush=True)
        return PathTracedResults(0, skipped=str(error))
    rendered = parts.render_split(out_dir / RENDERED_FOLDER, images_per_object, seed, progress=False)
    traced = out_dir / TRACED_FOLDER
    path_trace_split(rendered, traced, PathTraceSettings(), progress=True)
    scores = []
    for folder in (rendered, traced):
        split = read_eval_split([folder], rendered / BUILTIN_MODELS_FOLDER)
        results = evaluate_models(methods, split, vsd=False, progress=False)
        write_report(results, out_dir / f"eval_{folder.name}")
        scores.append(results[0])
    return PathTracedResults(images_per_object * len(parts.obj_ids), *scores,
                             mssd=paired_difference(*(_mssd_scores(result) for result in scores)))


def _mssd_scores(result: MethodResult) -> np.ndarray:
    diameters = {obj_id: float(info["diameter"]) for obj_id, info in result.split.models_info.items()}
    return instance_mssd_scores(result.errors.mssd_mm, result.errors.obj_id, diameters, result.thresholds)
