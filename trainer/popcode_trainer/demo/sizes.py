"""The demo's sizes: each a data, code, network and training budget (``PipelineSize``) with its time budget.

The quick size is what ``make demo`` runs; each choice in it was measured on
validation splits (the files under bench/results/ named beside it).
"""

from __future__ import annotations

from dataclasses import dataclass

from popcode_runtime.model.metadata import Representation

from ..detection.config import DetectorConfig
from ..train.config import Config, DataConfig
from ..train.network import NetworkConfig
from .report import POPCODE
from .steps import PipelineSize, small_config

BASELINE = Representation.SINGLE_VARIABLE
SCENE_SHARE = 0.25  # of every epoch's crops from the training scenes (bench/results/scene-mix-quick.md)
# Crops from detector-like boxes from the medium budget on: at about its crop-updates half of them halve what a
# detector's boxes cost in the bin (-6 points against -12) and keep the clean score; three quarters cost less
# again and lose nothing at 600 and at 2400 training scenes; at the quick budget they cost 5 points on the clean
# split (bench/results/box-noise-training.md).
MEDIUM_BOX_NOISE = ("detector", 0.75)
# The demo's detector: the chosen recipe (detection.config's defaults) for a fixed share of the budget on the
# training scenes, its epochs fitted to it (bench/results/detector-choices.md; its AP against minutes:
# bench/results/shipped-detector.md).
DEMO_DETECTOR = DetectorConfig(epochs=200)


@dataclass(frozen=True)
class DemoSize:
    """A demo budget and what it is for."""

    pipeline: PipelineSize
    purpose: str
    minutes: float | None = None  # fit the epochs so the whole demo takes about this long (epoch_budget)
    epoch_bounds: tuple[int, int] = (2, 1000)  # the fitted epochs stay within these (2: an anneal needs them)
    # ... or these when the models start from a pretrained start, which converges faster (None: the same)
    fine_tune_epoch_bounds: tuple[int, int] | None = None


DEMO_SIZES = {
    # quick's minutes leave the 15 of `make demo` room for creating .venv (about two minutes on a slow VM) and the
    # estimate's error: 13.5 took 15.8 minutes in all on an AVX2-only VM (README, Results).
    # 2000 images a part rather than 1000 and half the epochs: +3 to +5 MSSD at equal crop-updates on a
    # validation split, 4000 only 1 to 1.5 more at twice the rendering (bench/results/recipe.md, fourth round).
    # A quarter of the crops from cluttered scenes: +5 MSSD on a cluttered validation split for -2 on the clean
    # one (within its noise) at equal crop-updates; half or three quarters gain less (bench/results/scene-mix-quick.md).
    # Crops of detector-like boxes cost the clean split more than they gain at this budget
    # (bench/results/box-noise-training.md).
    "quick": DemoSize(PipelineSize(2000, 40, small_config(epochs=10, n_axes=642, n_angles=36), (POPCODE, BASELINE),
                                   cluttered_test_scenes=40, train_scenes=150, scene_share=SCENE_SHARE,
                                   detector_seconds=150.0, detector=DEMO_DETECTOR, path_traced_images=10),
                      "about 15 minutes on a 2-core CPU", minutes=12.0, epoch_bounds=(4, 40),
                      # from the shipped start, 2 epochs score more than 4 from random weights on validation parts
                      # and the built-in ones (bench/results/pretrained-start.md): a slow machine need not overrun
                      fine_tune_epoch_bounds=(2, 40)),
    "medium": DemoSize(PipelineSize(4000, 100, small_config(epochs=10, n_axes=642, n_angles=36,
                                                            box_noise=MEDIUM_BOX_NOISE), (POPCODE, BASELINE),
                                    cluttered_test_scenes=100, train_scenes=800, scene_share=SCENE_SHARE,
                                    detector_seconds=600.0, detector=DEMO_DETECTOR, path_traced_images=40),
                       "four times quick's time budget: about an hour", minutes=54.0, epoch_bounds=(5, 100)),
    # The paper's defaults (Config()), with data-loader workers for a GPU.
    "paper": DemoSize(PipelineSize(8000, 200, Config(data=DataConfig(num_workers=8)), (POPCODE, BASELINE),
                                   cluttered_test_scenes=200, train_scenes=4000, scene_share=SCENE_SHARE,
                                   detector_seconds=3600.0, detector=DEMO_DETECTOR, path_traced_images=100),
                      "the paper's code, network and schedule; for a GPU"),
}

# A size no help text offers: the README's own-parts test runs the one command at it, every step in seconds
# (its scores mean nothing).
SMOKE_NETWORK = NetworkConfig(conv_channels=(4, 4, 4), squeeze_channels=2, hidden=(16, 16, 16))
SMOKE_DETECTOR = DetectorConfig(input_width=128, input_height=96, widths=(4, 4, 8, 8, 8), fpn_channels=32,
                                head_convs=1, batch_size=2, score_threshold=0.01, max_detections=5)
HIDDEN_SIZES = {
    "smoke": DemoSize(PipelineSize(8, 2, small_config(epochs=2, n_axes=42, n_angles=12, network=SMOKE_NETWORK,
                                                      sigma_deg=30.0, batch_size=4), (POPCODE, BASELINE),
                                   cluttered_test_scenes=2, train_scenes=2, scene_share=0.5, detector_seconds=1.0,
                                   detector=SMOKE_DETECTOR, path_traced_images=1),
                      "every step in seconds, for tests; its scores mean nothing"),
}
SMOKE_LATENCY_ITERATIONS = 3
