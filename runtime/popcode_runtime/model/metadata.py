"""What a popcode ONNX model says about itself (docs/design.md#model-contract).

Everything the runtime needs to decode travels inside the model as
``metadata_props``: one key per field, each value JSON. The trainer writes it
with :meth:`ModelMetadata.to_props`; the runtime reads and checks it with
:meth:`ModelMetadata.from_props` and :meth:`ModelMetadata.check_output`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..base.checks import integer, mapping, number
from ..base.errors import PopcodeError
from ..base.files import name_id, parse_json
from ..base.limits import MAX_HULL_POINTS, MAX_METADATA_CHARS, MAX_OBJECTS
from ..base.text_enum import TextEnum
from ..coding.confidence import Calibrator
from ..coding.population_code import CodeLayout
from ..depth.surface_fit import object_surface
from ..geometry.crop import CROP_PADDING, CROP_SIZE, MAX_CROP_PADDING, MIN_CROP_PADDING
from ..geometry.symmetries import SymmetryClass, continuous_symmetries, discrete_transforms, symmetry_class
from ..geometry.translation import object_points_mm

FORMAT_VERSION = 1
INPUT_NAME = "image"
OUTPUT_NAME = "code"
MIN_INPUT_SIZE, MAX_INPUT_SIZE = 8, 1024  # crop side [px]; a batch of crops is N x size^2 floats
MAX_HYPOTHESES = 1024


class Representation(TextEnum):
    """The output representations; each decodes differently."""

    POPULATION_CODE = "population_code"
    ONE_HOT = "one_hot"
    SINGLE_VARIABLE = "single_variable"
    MULTI_HYPOTHESIS = "multi_hypothesis"


GRID_REPRESENTATIONS = (Representation.POPULATION_CODE, Representation.ONE_HOT)  # outputs one value per neuron


class RotationFrame(TextEnum):
    """Which rotation the network predicts: in the camera frame, or as seen along the ray."""

    EGOCENTRIC = "egocentric"
    ALLOCENTRIC = "allocentric"


@dataclass(frozen=True)
class ModelMetadata:
    """Decoded metadata of a popcode model.

    ``objects`` maps BOP object ids to their ``models_info.json`` entries.
    ``output_dim`` is the length of one output row; for the grid
    representations it must equal ``code.size``. ``num_hypotheses`` is the M
    of the multiple-hypotheses baseline.
    """

    representation: Representation
    code: CodeLayout
    objects: dict[int, dict[str, Any]]
    rotation_frame: RotationFrame = RotationFrame.EGOCENTRIC
    input_size: int = CROP_SIZE
    crop_padding: float = CROP_PADDING
    num_hypotheses: int = 0
    training: dict[str, Any] = field(default_factory=dict)
    confidence: Calibrator | None = None  # fitted at export on held-out crops; None: no calibrated confidence
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        if self.representation not in Representation.values():
            raise PopcodeError(
                f"unknown representation {self.representation!r}; expected one of {Representation.values()}"
            )
        if self.rotation_frame not in RotationFrame.values():
            raise PopcodeError(
                f"unknown rotation_frame {self.rotation_frame!r}; expected one of {RotationFrame.values()}"
            )
        object.__setattr__(self, "representation", Representation(self.representation))
        object.__setattr__(self, "rotation_frame", RotationFrame(self.rotation_frame))
        if not isinstance(self.code, CodeLayout):
            raise PopcodeError(f"metadata code must be a CodeLayout, got {type(self.code).__name__}")
        object.__setattr__(self, "input_size", integer(self.input_size, "input size", MIN_INPUT_SIZE, MAX_INPUT_SIZE))
        object.__setattr__(self, "crop_padding", number(self.crop_padding, "input crop_padding", MIN_CROP_PADDING,
                                                        MAX_CROP_PADDING))
        object.__setattr__(self, "num_hypotheses", integer(self.num_hypotheses, "num_hypotheses", 0, MAX_HYPOTHESES))
        mapping(self.training, "training")
        if not isinstance(self.objects, Mapping) or not self.objects:
            raise PopcodeError("metadata lists no objects")
        if len(self.objects) > MAX_OBJECTS:
            raise PopcodeError(f"metadata lists {len(self.objects)} objects, more than the limit of {MAX_OBJECTS}")
        for obj_id, info in self.objects.items():
            check_object_info(obj_id, info)
        classes = {symmetry_class(info) for info in self.objects.values()}
        continuous = SymmetryClass.CONTINUOUS in classes
        if continuous and len(classes) > 1:
            raise PopcodeError("objects with and without a continuous symmetry cannot share one model")
        if continuous != self.code.axis_only:
            raise PopcodeError(
                "code.axis_only must be true exactly when the objects have a continuous symmetry"
            )
        if self.representation == Representation.MULTI_HYPOTHESIS and self.num_hypotheses < 1:
            raise PopcodeError("a multi_hypothesis model needs num_hypotheses >= 1")
        if self.confidence is not None and self.representation not in GRID_REPRESENTATIONS:
            raise PopcodeError(f"a confidence calibrator reads a population code; a {self.representation} model "
                               "cannot carry one")

    @property
    def output_dim(self) -> int:
        """Length of one output row that this metadata implies."""
        if self.representation in GRID_REPRESENTATIONS:
            return self.code.size
        if self.representation == Representation.SINGLE_VARIABLE:
            return 3 if self.code.axis_only else 6
        return 4 * self.num_hypotheses

    def check_output(self, output_shape: list[Any]) -> None:
        """Refuse a model whose declared output shape disagrees with the metadata."""
        if len(output_shape) != 2:
            raise PopcodeError(f"output '{OUTPUT_NAME}' must be 2-D [N, D], the model declares {output_shape}")
        width = output_shape[1]
        if isinstance(width, int) and width != self.output_dim:
            raise PopcodeError(
                f"output '{OUTPUT_NAME}' has {width} values per crop but the metadata "
                f"({self.representation}, code size {self.code.size}) implies {self.output_dim}"
            )

    def to_props(self) -> dict[str, str]:
        """``metadata_props`` entries: one key per field, JSON values."""
        return {
            "popcode.format_version": json.dumps(self.format_version),
            "popcode.representation": json.dumps(self.representation),
            "popcode.code": json.dumps(self.code.to_dict()),
            "popcode.objects": json.dumps({str(k): v for k, v in self.objects.items()}),
            "popcode.rotation_frame": json.dumps(self.rotation_frame),
            "popcode.input": json.dumps({"size": self.input_size, "crop_padding": self.crop_padding}),
            "popcode.num_hypotheses": json.dumps(self.num_hypotheses),
            "popcode.training": json.dumps(self.training),
            "popcode.confidence": json.dumps(None if self.confidence is None else self.confidence.to_dict()),
        }

    @classmethod
    def from_props(cls, props: Mapping[str, str]) -> ModelMetadata:
        """Parse ``metadata_props``; names the key that is missing or malformed.

        Values are JSON without NaN or Infinity; every number is checked for its
        type and range before anything is sized by it.
        """
        if "popcode.format_version" not in props:
            raise PopcodeError("not a popcode model: its metadata has no 'popcode.format_version'")
        chars = sum(len(value) for value in props.values())
        if chars > MAX_METADATA_CHARS:
            raise PopcodeError(f"the model's metadata holds {chars:,} characters, more than the limit of "
                               f"{MAX_METADATA_CHARS:,}: export fewer objects per model")

        def load(key: str, default: Any = None) -> Any:
            if key not in props:
                if default is not None:
                    return default
                raise PopcodeError(f"model metadata lacks '{key}'")
            return parse_json(props[key], f"model metadata '{key}'")

        version = load("popcode.format_version")
        if version != FORMAT_VERSION or isinstance(version, bool):
            raise PopcodeError(
                f"model format version {version!r} is not supported by this runtime (it reads {FORMAT_VERSION})"
            )
        objects = mapping(load("popcode.objects"), "model metadata 'popcode.objects'")
        input_info = mapping(load("popcode.input"), "model metadata 'popcode.input'")
        object_map = {}
        for key, info in objects.items():
            obj_id = name_id(key)
            if obj_id is None:
                raise PopcodeError(f"model metadata 'popcode.objects': object id {key[:40]!r} is not a whole number "
                                   "of at most 18 digits")
            object_map[obj_id] = dict(mapping(info, f"object {key}"))
        return cls(
            representation=load("popcode.representation"),
            code=CodeLayout.from_dict(mapping(load("popcode.code"), "model metadata 'popcode.code'")),
            objects=object_map,
            rotation_frame=load("popcode.rotation_frame"),
            input_size=input_info.get("size", CROP_SIZE),
            crop_padding=input_info.get("crop_padding", CROP_PADDING),
            num_hypotheses=load("popcode.num_hypotheses", 0),
            training=load("popcode.training", {}),
            confidence=_calibrator(load("popcode.confidence")) if "popcode.confidence" in props else None,
            format_version=version,
        )


def _calibrator(value: Any) -> Calibrator | None:
    """The optional confidence calibrator (null in models exported without one)."""
    return None if value is None else Calibrator.from_dict(value)


def check_object_info(obj_id: Any, info: Any) -> None:
    """An object's entry must be a BOP ``models_info`` mapping with sound numbers; the error names the object.

    The trainer checks a models folder's entries with this too. Symmetries are read, never expanded: their
    count is checked before any matrix is read (:mod:`popcode_runtime.geometry.symmetries`).
    """
    integer(obj_id, "object id", 0)
    info = mapping(info, f"object {obj_id}")
    try:
        for key in ("diameter", "size_x", "size_y", "size_z"):
            if key in info:
                number(info[key], key, 0.0)
        for key in ("min_x", "min_y", "min_z"):
            if key in info:
                number(info[key], key)
        discrete_transforms(info)
        continuous_symmetries(info)
        if "hull_points_mm" in info:  # checked now, not at the first call that asks for a translation
            if isinstance(info["hull_points_mm"], list) and len(info["hull_points_mm"]) > MAX_HULL_POINTS:
                raise PopcodeError(f"hull_points_mm lists {len(info['hull_points_mm'])} points; at most "
                                   f"{MAX_HULL_POINTS} are allowed (every box fit projects them all)")
            object_points_mm(info)
        object_surface(info)  # likewise the surface points that depth needs, where the model has them
    except PopcodeError as error:
        raise PopcodeError(f"object {obj_id}: {error}") from error
