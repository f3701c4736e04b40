"""Poses from depth in evaluation: the runtime's predict with each image's depth image, scored as full 6-D poses.

A robot with a depth camera places each instance as
``PoseEstimator.predict(depth=..., refine_depth=...)`` does
(:mod:`popcode_runtime.depth.placement`). The evaluation runs a method's models
through the runtime's per-image loop with the split's depth images (``depth/``,
``scene_camera.json``'s ``depth_scale``), so what is scored is what ``popcode
run --depth [--refine]`` writes: per mode (:data:`DEPTH`: the translation from
depth; :data:`REFINED`: rotation and translation refined against the observed
points) the 6-D errors and scores, where each translation came from, why depth
was not used where it was not (the runtime's ``depth_note``), and the seconds
of the depth step (``Timings.depth_s``: the box fit it starts from, the depth's
translation and the refinement).
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.depth.icp import require_small_gicp
from popcode_runtime.inference.image_loop import estimate_images, group_by_image

from ...data.bop import Instance
from ...metrics.recall import InstanceErrors
from .models import Method
from .split import EvalSplit
from .split_metrics import SplitMetrics


@dataclass(frozen=True)
class DepthMode:
    """One way of using the depth image: a table row's suffix, a file or column suffix, and whether it refines."""

    label: str
    key: str
    refine: bool


DEPTH = DepthMode("depth", "depth", refine=False)
REFINED = DepthMode("depth + ICP", "refined", refine=True)


def depth_modes(refine: bool) -> tuple[DepthMode, ...]:
    """The modes an evaluation with depth scores: the depth's translation, and with ``refine`` the refined pose."""
    return (DEPTH, REFINED) if refine else (DEPTH,)


@dataclass(frozen=True)
class DepthPoses:
    """One method's 6-D poses with depth in one mode, in split order."""

    mode: DepthMode
    R_m2c: np.ndarray  # (N, 3, 3): the code's rotation, or the refined one where refinement was kept
    t_m2c_mm: np.ndarray  # (N, 3)
    sources: tuple[str, ...]  # (N,) each translation's source: box, depth or refined
    notes: tuple[str | None, ...]  # (N,) why depth was not (fully) used; None where it was
    depth_s: np.ndarray  # (N,) the instance's share of its image's depth step
    errors: InstanceErrors  # of (R_m2c, t_m2c_mm)
    per_object: dict[int, dict[str, float]]
    groups: dict[str, dict[str, float]]

    def source_counts(self) -> dict[str, int]:
        """Instances per translation source, most first."""
        return dict(Counter(self.sources).most_common())

    def note_counts(self) -> dict[str, int]:
        """Instances per kind of note (:func:`note_kind`), most first; those depth placed as asked have none."""
        return dict(Counter(note_kind(note) for note in self.notes if note is not None).most_common())


def note_kind(note: str) -> str:
    """A ``depth_note`` without its numbers, so that notes of one cause count together."""
    return note.split(":")[0].split(";")[0].split(" (")[0]


def require_depth(split: EvalSplit) -> None:
    """Every instance's image has a depth image, else one line naming the scene folder of the first without."""
    lacking = [inst for inst in split.instances if inst.depth_path is None]
    if lacking:
        scene = lacking[0].image_path.parent.parent
        raise PopcodeError(f"{len(lacking)} of {len(split.instances)} instances have no depth image (first: "
                           f"{lacking[0].image_path}, nothing for it in {scene / 'depth'}): --depth reads each "
                           "image's depth, as popcode-train render writes it")


def check_depth_models(method: Method, obj_ids: Sequence[int], refine: bool) -> None:
    """Before any prediction: each model carries the surface points of its objects, and refinement its library."""
    for model in method.models:
        for obj_id in sorted(set(obj_ids) & set(model.obj_ids)):
            try:
                model.estimator.object_surface(obj_id)
            except PopcodeError as error:
                raise PopcodeError(f"{model.path}: {error}") from error
    if refine:
        require_small_gicp()


def predict_with_depth(method: Method, instances: Sequence[Instance], mode: DepthMode, top_k: int = 1,
                       progress: bool = True) -> tuple[np.ndarray, np.ndarray, list[str], list[str | None], np.ndarray]:
    """Each instance's rotation, translation, its source and note, and its share of the depth step's seconds.

    One ``predict`` per image and model with the image's depth, through the
    runtime's per-image loop; a population code's refinement starts from the
    code's ``top_k`` strongest poses (at least the runtime's ``REFINE_STARTS``)
    and keeps the best fit, as ``popcode predict [--top-k K] --refine`` does.
    """
    images = [dataclasses.replace(image, depth_path=instances[image.key[0]].depth_path,
                                  depth_scale=instances[image.key[0]].depth_scale)
              for image in group_by_image(instances)]
    options = {"refine_depth": mode.refine}
    if mode.refine and top_k > 1 and method.population_code:
        options["top_k"] = top_k
    R, t_mm = np.empty((len(instances), 3, 3)), np.empty((len(instances), 3))
    sources: list[str] = [""] * len(instances)
    notes: list[str | None] = [None] * len(instances)
    depth_s = np.empty(len(instances))
    for done in tqdm(estimate_images(method.estimators, method.paths, images, **options), total=len(images),
                     desc=f"{method.name}, {mode.label}", unit="img", disable=not progress):
        rows = list(done.key)
        # each model of the image ran one predict call, so its last timings are this image's
        depth_s[rows] = sum(estimator.last_timings.depth_s for estimator, _ in done.by_model) / len(rows)
        for row, prediction in zip(rows, done.predictions, strict=True):
            R[row], t_mm[row] = prediction.R_m2c, prediction.t_m2c_mm
            sources[row], notes[row] = str(prediction.t_source), prediction.depth_note
    return R, t_mm, sources, notes, depth_s


def depth_poses(method: Method, metrics: SplitMetrics, mode: DepthMode, top_k: int = 1,
                progress: bool = True) -> DepthPoses:
    """The method's poses with depth in ``mode`` on the split's instances, scored as full 6-D poses."""
    R, t_mm, sources, notes, depth_s = predict_with_depth(method, metrics.split.instances, mode, top_k, progress)
    errors = metrics.errors(R, t_mm)
    return DepthPoses(mode, R, t_mm, tuple(sources), tuple(notes), depth_s, errors, *metrics.scores(errors))
