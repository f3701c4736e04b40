"""The demo's plan: its steps with estimated seconds, announced one by one with the time left overall.

The estimates are in seconds of the 2-core CPU the project is developed on;
the plan rescales what is left by how long the finished steps really took.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager

import numpy as np

from .steps import SMALL_NETWORK, PipelineSize

FIRST_EPOCHS = "time the first epoch of every model"
DETECTOR_STAGE = "train the detector"
PATH_TRACED_STAGE = "path-traced test images"
# Seconds per unit on the 2-core CPU this project is developed on (small network, 642 x 36 code); the
# plan rescales its estimate by how long the finished steps really took, so other machines converge.
SECONDS_PER_RENDERED_IMAGE = 0.008
SECONDS_PER_TRAINING_SCENE = 0.45  # 720 x 540, about seven parts (bench/results/scene-render-speed.md)
SECONDS_PER_TRAINING_SAMPLE = 0.0035
SECONDS_PER_EXPORT = 10.0  # ONNX, quantisation and the confidence fit of one model
SECONDS_PER_EVALUATED_INSTANCE = 0.05
# The population code's rows with depth on the clean test split (depth, depth + ICP): on a quick run's models they
# added 31 + 24 s to the 151 s that scoring its 240 instances took (a busy 2-core VM), whose estimate is 48 s.
SECONDS_PER_DEPTH_INSTANCE = 0.07
SECONDS_PER_CLUTTERED_SCENE = 1.0  # rendering (0.3 s) and scoring its ~6.5 instances with two methods
SECONDS_DETECTOR_EXPORT = 15.0  # the detector's frames read, its ONNX export and parity check
SECONDS_PER_DETECTED_SCENE = 0.6  # the own detector's boxes, the poses in them and their scoring
SECONDS_PER_TRACED_IMAGE = 0.2  # 128 x 128 at 32 samples a pixel (bench/results/path-traced.md)
SECONDS_LATENCY = 10.0
SECONDS_FIGURES = 10.0


class StagePlan:
    """Named steps with estimated seconds; announces each with the time left overall.

    The estimate of what is left is scaled by (time taken / time estimated) of
    the finished steps, so a faster or slower machine corrects it as it goes. A ``fixed`` step takes the
    seconds it is given on any machine (the detector trains for a time budget): it says nothing of the
    machine's speed, so it neither sets the scale nor is scaled (counted, it pulled the scale towards 1 and a
    fast machine's demo reserved twice what its scoring steps took: bench/results/demo-minutes.md).
    """

    def __init__(self, stages: Sequence[tuple[str, float]], fixed: Collection[str] = ()) -> None:
        self.estimates = dict(stages)
        self.fixed = frozenset(fixed)
        self.done: dict[str, float] = {}

    @property
    def scale(self) -> float:
        """Seconds taken per second estimated over the finished steps but the fixed ones (1 before any)."""
        measured = [name for name in self.done if name not in self.fixed]
        estimated_done = sum(self.estimates[name] for name in measured)
        return sum(self.done[name] for name in measured) / estimated_done if estimated_done > 0 else 1.0

    def remaining_s(self, after: Sequence[str] = ()) -> float:
        left = [name for name in self.estimates if name not in self.done and name not in after]
        return sum(self.estimates[name] * (1.0 if name in self.fixed else self.scale) for name in left)

    def revise(self, estimates: Mapping[str, float]) -> None:
        """New estimates for steps not yet done (the finished ones keep theirs, which set the scale)."""
        self.estimates.update({name: s for name, s in estimates.items() if name not in self.done})

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        index = list(self.estimates).index(name) + 1
        this_step = self.remaining_s() - self.remaining_s([name])
        print(f"\n[{index}/{len(self.estimates)}] {name}: about {minutes_text(this_step)}; "
              f"about {minutes_text(self.remaining_s())} left overall", flush=True)
        started = time.perf_counter()
        yield
        self.done[name] = time.perf_counter() - started


def minutes_text(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def plan(size: PipelineSize, groups: Sequence[Sequence[int]], objects: int, fit_epochs: bool = False) -> StagePlan:
    """The demo's steps with their estimated seconds on the reference CPU; with ``fit_epochs`` a step trains the
    first epoch of every model and the training steps the rest."""
    images = objects * (size.train_images_per_object + size.test_images_per_object)
    width = np.prod(size.config.network.conv_channels) / np.prod(SMALL_NETWORK.conv_channels)
    per_epoch = {(representation, tuple(obj_ids)): len(obj_ids) * size.train_images_per_object
                 * SECONDS_PER_TRAINING_SAMPLE * max(1.0, width ** (1 / 3))
                 for representation in size.representations for obj_ids in groups}
    traced = objects * size.traced_train_images * (SECONDS_PER_RENDERED_IMAGE + SECONDS_PER_TRACED_IMAGE)
    stages = [("render", images * SECONDS_PER_RENDERED_IMAGE + size.train_scenes * SECONDS_PER_TRAINING_SCENE
               + traced)]
    if size.detector_seconds:
        stages.append((DETECTOR_STAGE, size.detector_seconds + SECONDS_DETECTOR_EXPORT))
    if fit_epochs:
        stages.append((FIRST_EPOCHS, sum(per_epoch.values())))
    for (representation, obj_ids), seconds in per_epoch.items():
        stages.append((train_stage(representation, obj_ids),
                       seconds * (size.config.train.epochs - fit_epochs) + SECONDS_PER_EXPORT))
    methods = len(size.representations) + 2  # + refined decoder + quantised model
    stages += [("evaluate", objects * size.test_images_per_object
                * (methods * SECONDS_PER_EVALUATED_INSTANCE + SECONDS_PER_DEPTH_INSTANCE))]
    if size.cluttered_test_scenes:
        own_detector = SECONDS_PER_DETECTED_SCENE if size.detector_seconds else 0.0
        stages.append(("cluttered test split",
                       size.cluttered_test_scenes * (SECONDS_PER_CLUTTERED_SCENE + own_detector)))
    if size.path_traced_images:
        stages.append((PATH_TRACED_STAGE, objects * size.path_traced_images
                       * (SECONDS_PER_TRACED_IMAGE + 2 * SECONDS_PER_EVALUATED_INSTANCE)))
    stages += [("latency", SECONDS_LATENCY), ("figures", SECONDS_FIGURES)]
    return StagePlan(stages, fixed=[DETECTOR_STAGE] if size.detector_seconds else [])


def train_stage(representation: str, obj_ids: Sequence[int]) -> str:
    """The name of the step that trains and exports one model."""
    return f"train {representation} for objects {', '.join(map(str, obj_ids))}"
