"""popcode runtime: crop, infer and decode object rotations from a population-code ONNX model.

Needs only numpy, onnxruntime and OpenCV. The trainer imports the code layout,
rotation maths, crop and decoding from here, so there is one definition of each.
"""

from pathlib import Path

__version__ = (Path(__file__).parent / "VERSION").read_text(encoding="utf-8").strip()  # the one place: VERSION

from .base.errors import PopcodeError
from .coding.population_code import CodeLayout, DecodedRotations, PopulationCode, fibonacci_lattice
from .geometry.camera import parse_camera_matrix
from .geometry.crop import crop_batch, crop_square, read_image, to_grey
from .geometry.symmetries import SymmetryClass, symmetry_class, symmetry_rotations, symmetry_transforms
from .inference.detector import DetectedBox, Detector
from .inference.estimator import PoseEstimator
from .inference.frame import FramePose, FramePoseEstimator
from .inference.prediction import Prediction
from .model.metadata import ModelMetadata, Representation, RotationFrame

__all__ = [
    "CodeLayout",
    "DecodedRotations",
    "DetectedBox",
    "Detector",
    "FramePose",
    "FramePoseEstimator",
    "ModelMetadata",
    "PopcodeError",
    "PopulationCode",
    "PoseEstimator",
    "Prediction",
    "Representation",
    "RotationFrame",
    "SymmetryClass",
    "crop_batch",
    "crop_square",
    "fibonacci_lattice",
    "parse_camera_matrix",
    "read_image",
    "symmetry_class",
    "symmetry_rotations",
    "symmetry_transforms",
    "to_grey",
]
