"""A kit's time budget in hours mapped onto the demo pipeline's sizes.

Three anchors span the mapping: the quick demo's data (12 minutes), the medium demo's (54 minutes, where
detector-like training boxes start to pay: bench/results/box-noise-training.md) and the shipped models'
recipe (``models/README.md``: 2400 training scenes, a trunk three times as wide, a quarter of the crops path
traced; about four hours of a 2-core CPU with its detector). Between two anchors the data sizes are
interpolated in log-hours; the recipe's choices (box noise, network, path-traced share) switch on at their
anchor; past the last anchor the data stay the shipped recipe's and the extra hours buy epochs. The detector
always gets :data:`DETECTOR_SHARE` of the budget, about the demo's share. Within each size the epochs are
fitted to the budget on the machine that runs it (:mod:`popcode_trainer.demo.epoch_budget`), a CUDA device
included. Measured from 0.2 to 1 hour on the project's validation parts, the detector's share at 0.5 hour
(bench/results/kit-hours-validation-parts.md); above 1 hour not yet (issue 63).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from popcode_runtime.base.errors import PopcodeError

from ..data.path_trace import import_mitsuba
from ..demo.report import POPCODE
from ..demo.sizes import DEMO_DETECTOR, DEMO_SIZES, MEDIUM_BOX_NOISE, SCENE_SHARE
from ..demo.steps import SMALL_NETWORK, PipelineSize, small_config
from ..train.network import NetworkConfig

MIN_HOURS = DEMO_SIZES["quick"].minutes / 60.0  # under the quick demo's budget the fixed steps leave no training
MAX_HOURS = 168.0  # a week: a longer budget is a typo (or the data would outgrow any disk long before)
# of the budget; twice as much bought the detector little at 0.5 h (bench/results/kit-hours-validation-parts.md)
DETECTOR_SHARE = 0.2
# The shipped 3-6 model's trunk (tools.recipes.NETWORKS["small-x3"]): 3.8 points more in a bin on validation
# (bench/results/network-width.md). No pretrained start is shipped for it yet, so it starts from random weights.
WIDE_NETWORK = replace(SMALL_NETWORK, conv_channels=(48, 96, 192), squeeze_channels=24, hidden=(256, 128, 128))
TRACED_SHARE = 0.25  # of every epoch's crops path traced, as the shipped models' eighth refresh


@dataclass(frozen=True)
class Anchor:
    """The data sizes and recipe choices of one budget the mapping passes through."""

    hours: float
    train_images: int  # per part
    train_scenes: int
    test_images: int  # per part
    cluttered_test_scenes: int
    path_traced_images: int  # per part, of the test images
    traced_train_images: int = 0  # per part, path traced for training
    box_noise: tuple[str, float] = ("none", 1.0)
    network: NetworkConfig = SMALL_NETWORK


ANCHORS = (
    Anchor(MIN_HOURS, 2000, 150, 40, 40, 10),  # the quick demo's data
    Anchor(DEMO_SIZES["medium"].minutes / 60.0, 4000, 800, 100, 100, 40, box_noise=MEDIUM_BOX_NOISE),
    Anchor(4.0, 4000, 2400, 100, 100, 40, traced_train_images=1000, box_noise=MEDIUM_BOX_NOISE,
           network=WIDE_NETWORK),  # the shipped recipe
)


def check_hours(hours: float) -> float:
    """``hours`` if a kit can be made in it, else one line that says the range."""
    if not math.isfinite(hours) or hours <= 0:
        raise PopcodeError(f"--hours must be a positive number of hours, not {hours}")
    if hours < MIN_HOURS:
        raise PopcodeError(f"--hours {hours:g} is too little to train anything: a kit needs at least {MIN_HOURS:g} h "
                           f"({60 * MIN_HOURS:g} minutes, the quick demo's budget)")
    if hours > MAX_HOURS:
        raise PopcodeError(f"--hours {hours:g} is more than a kit can use: at most {MAX_HOURS:g} (a week)")
    return hours


def kit_size(hours: float, path_tracing: bool | None = None) -> PipelineSize:
    """The pipeline a budget of ``hours`` trains: the population code alone, the data interpolated between the
    anchors around ``hours``, the recipe of the highest anchor at or below it, the detector's share of the time.
    ``path_tracing``: whether Mitsuba is there for path-traced training crops (None: look)."""
    hours = check_hours(hours)
    low = max((a for a in ANCHORS if a.hours <= hours), key=lambda a: a.hours)
    high = min((a for a in ANCHORS if a.hours >= hours), key=lambda a: a.hours, default=low)
    weight = 0.0 if high is low else math.log(hours / low.hours) / math.log(high.hours / low.hours)

    def between(field: str) -> int:
        return round(getattr(low, field) + weight * (getattr(high, field) - getattr(low, field)))

    if path_tracing is None:
        path_tracing = _has_mitsuba()
    traced = low.traced_train_images if path_tracing else 0
    quick = DEMO_SIZES["quick"].pipeline.config.code
    config = small_config(epochs=2, n_axes=quick.n_axes, n_angles=quick.n_angles, network=low.network,
                          box_noise=low.box_noise)
    return PipelineSize(between("train_images"), between("test_images"), config, (POPCODE,),
                        cluttered_test_scenes=between("cluttered_test_scenes"), train_scenes=between("train_scenes"),
                        scene_share=SCENE_SHARE, detector_seconds=3600.0 * hours * DETECTOR_SHARE,
                        detector=DEMO_DETECTOR, path_traced_images=between("path_traced_images"),
                        traced_train_images=traced, traced_share=TRACED_SHARE if traced else 0.0)


def _has_mitsuba() -> bool:
    try:
        import_mitsuba()
    except PopcodeError:
        return False
    return True
