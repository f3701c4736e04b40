"""The demo's tiny size, shared by the tests of the whole demo and of its steps: it runs in a minute on a CPU."""

from __future__ import annotations

from popcode_trainer.demo.steps import PipelineSize, small_config
from popcode_trainer.detection.config import DetectorConfig
from popcode_trainer.train.network import NetworkConfig

TINY_NETWORK = NetworkConfig(conv_channels=(4, 4, 4), squeeze_channels=2, hidden=(16, 16, 16))
# A detector that trains for a second and keeps its five best boxes a frame, however poor: the report's section
# on the run's own eyes is filled either way.
TINY_DETECTOR = DetectorConfig(input_width=128, input_height=96, widths=(4, 4, 8, 8, 8), fpn_channels=32,
                               head_convs=1, batch_size=2, score_threshold=0.01, max_detections=5)
TINY = PipelineSize(8, 2, small_config(epochs=1, n_axes=42, n_angles=12, network=TINY_NETWORK, sigma_deg=30.0,
                                       batch_size=4), ("population_code", "single_variable"), cluttered_test_scenes=2,
                    train_scenes=2, scene_share=0.5, detector_seconds=1.0, detector=TINY_DETECTOR, path_traced_images=1)
