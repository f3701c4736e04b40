"""``PoseEstimator``: a popcode model behind one call, image + boxes -> rotations (the one inference pipeline)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..base.checks import flag, integer
from ..base.errors import PopcodeError
from ..coding.confidence import code_features
from ..coding.hypotheses import Hypothesis, find_hypotheses
from ..coding.population_code import PopulationCode
from ..depth.icp import require_small_gicp
from ..depth.placement import pose_with_depth
from ..depth.surface_fit import ObjectSurface, TranslationSource, check_depth, object_surface
from ..geometry.camera import parse_camera_matrix
from ..geometry.crop import box_centre, check_image, crop_batch
from ..geometry.rotations import allocentric_to_egocentric, matrix_to_axis_angle
from ..geometry.symmetries import symmetry_rotations
from ..geometry.translation import object_points_mm, translation_from_box
from ..model.decoding import check_decoder, decode_output
from ..model.engine import Engine, OnnxEngine
from ..model.metadata import ModelMetadata, Representation, RotationFrame

MAX_BOXES_PER_CALL = 10_000  # predict runs them in chunks; a robot's image holds far fewer
MAX_CHUNK = 256  # crops per engine call
MAX_TOP_K = 100
MEMORY_BUDGET_BYTES = 1 << 30  # crops + outputs held at once by one call


@dataclass(frozen=True)
class Prediction:
    """The rotation of one object instance (model-to-camera, OpenCV camera frame), and its translation when asked.

    With ``refine_depth`` the rotation is the one refined against the depth
    (``t_source`` ``refined``); ``score``, ``confidence`` and ``hypotheses``
    stay those of the code.
    """

    R_m2c: np.ndarray  # (3, 3)
    axis: np.ndarray  # (3,) unit rotation axis of R_m2c
    angle_rad: float  # rotation angle of R_m2c in [0, pi]
    score: float  # peak activation (population code) or the representation's own score
    box: tuple[float, float, float, float]
    obj_id: int | None  # None when a model of several objects was not told which
    code: np.ndarray | None = None  # raw network output, when asked for
    t_m2c_mm: np.ndarray | None = None  # (3,) translation, when asked for (from the box, or from depth when given)
    hypotheses: list[Hypothesis] | None = None  # every distinct pose, strongest first, when top_k > 1
    confidence: float | None = None  # P(rotation error < the model's threshold); None without a calibrator
    t_source: TranslationSource | None = None  # where t_m2c_mm came from; None without a translation
    depth_fit: float | None = None  # share of the visible surface the depth confirms less the share it sees through
    depth_note: str | None = None  # why the depth was not (fully) used for this instance; None when it was

    def to_dict(self) -> dict:
        data = {
            "box": list(self.box),
            "obj_id": self.obj_id,
            "R_m2c": self.R_m2c.tolist(),
            "axis": self.axis.tolist(),
            "angle_deg": float(np.degrees(self.angle_rad)),
            "score": self.score,
            "confidence": self.confidence,
        }
        if self.t_m2c_mm is not None:
            data["t_m2c_mm"] = self.t_m2c_mm.tolist()
            data["t_source"] = None if self.t_source is None else str(self.t_source)
        if self.depth_fit is not None:
            data["depth_fit"] = self.depth_fit
        if self.depth_note is not None:
            data["depth_note"] = self.depth_note
        if self.hypotheses is not None:
            data["hypotheses"] = [
                {"R_m2c": h.R_m2c.tolist(), "activation": h.activation, "score": h.score,
                 "equivalent": h.equivalent.tolist()}
                for h in self.hypotheses
            ]
        if self.code is not None:
            data["code"] = self.code.tolist()
        return data


@dataclass(frozen=True)
class Timings:
    """Seconds spent per stage of the last call."""

    crop_s: float
    inference_s: float
    decode_s: float  # decoding, frame conversion and the translation from the box
    depth_s: float = 0.0  # the translation from depth and the refinement


class PoseEstimator:
    """Crop -> engine -> decode -> camera frame: ``predict(image, boxes)`` in one batched run.

    ``PoseEstimator(path)`` runs a popcode ONNX model with onnxruntime
    (``providers``; ``threads``: its intra-op threads, 0: all cores);
    :meth:`from_engine` runs any other engine with the model's metadata (the
    trainer's torch engine for checkpoints). ``decoder`` is ``argmax`` (the
    paper's) or ``refined`` (sub-neuron estimate).
    """

    def __init__(self, model_path: str | Path, providers: Sequence[str] | None = None, threads: int = 0,
                 decoder: str = "argmax") -> None:
        check_decoder(decoder)
        engine = OnnxEngine(model_path, providers, threads)
        self._attach(engine, engine.metadata, decoder)

    @classmethod
    def from_engine(cls, engine: Engine, metadata: ModelMetadata, decoder: str = "argmax") -> PoseEstimator:
        """An estimator over ``engine`` (crops ``(N, 1, S, S)`` float32 -> ``(N, metadata.output_dim)`` float32).

        ``metadata`` is the model's, as its ONNX export would carry it: it
        says how to crop, decode and convert the engine's outputs.
        """
        check_decoder(decoder)
        estimator = cls.__new__(cls)
        estimator._attach(engine, metadata, decoder)
        return estimator

    def _attach(self, engine: Engine, metadata: ModelMetadata, decoder: str) -> None:
        check_decoder(decoder, metadata)
        self.engine, self.metadata, self.decoder = engine, metadata, decoder
        self.last_timings = Timings(0.0, 0.0, 0.0, 0.0)
        # parsed once: the confidence and the hypotheses of every box need the object's symmetry rotations
        self._symmetries = {obj_id: symmetry_rotations(info) for obj_id, info in metadata.objects.items()}
        self._surfaces = {obj_id: object_surface(info) for obj_id, info in metadata.objects.items()}

    @property
    def providers(self) -> list[str]:
        """onnxruntime's execution providers for an ONNX engine; empty for other engines."""
        return self.engine.providers if isinstance(self.engine, OnnxEngine) else []

    def run(self, crops: np.ndarray) -> np.ndarray:
        """Raw network output ``(N, D)`` float32 for crops ``(N, 1, S, S)`` float32 in [0, 1].

        The engine sees at most :attr:`chunk_size` crops per call (exactly that
        many for a model with a fixed batch axis, the last chunk zero-padded).
        """
        size = self.metadata.input_size
        if (not isinstance(crops, np.ndarray) or crops.ndim != 4 or crops.shape[1:] != (1, size, size)
                or crops.dtype != np.float32):
            shape = getattr(crops, "shape", type(crops).__name__)
            raise PopcodeError(f"crops must be float32 [N, 1, {size}, {size}], got {getattr(crops, 'dtype', '')} "
                               f"{shape}")
        if len(crops) * self.metadata.output_dim * 4 > MEMORY_BUDGET_BYTES:
            raise PopcodeError(f"{len(crops)} crops x {self.metadata.output_dim} outputs exceed the runtime's memory "
                               f"budget of {MEMORY_BUDGET_BYTES >> 20} MiB; run fewer at a time")
        chunk = self.chunk_size
        fixed = getattr(self.engine, "max_batch", None) is not None
        outputs = []
        for start in range(0, len(crops), chunk):
            part = crops[start : start + chunk]
            count = len(part)
            if fixed and count < chunk:
                part = np.concatenate([part, np.zeros((chunk - count, *part.shape[1:]), np.float32)])
            outputs.append(self._checked(self.engine(part), len(part))[:count])
        if not outputs:
            return np.empty((0, self.metadata.output_dim), np.float32)
        return outputs[0] if len(outputs) == 1 else np.concatenate(outputs)

    def _checked(self, output: np.ndarray, count: int) -> np.ndarray:
        expected = (count, self.metadata.output_dim)
        if not isinstance(output, np.ndarray):
            raise PopcodeError(f"the engine returned a {type(output).__name__}, not a numpy array {expected}")
        if output.shape != expected or output.dtype != np.float32:
            raise PopcodeError(f"the engine returned {output.dtype} {output.shape}; the model's metadata implies "
                               f"float32 {expected}")
        return output

    @property
    def chunk_size(self) -> int:
        """Crops per engine call: the model's fixed batch, else as many as the memory budget allows (at most 256)."""
        fixed = getattr(self.engine, "max_batch", None)
        if fixed is not None:
            return fixed
        per_crop = 4 * (self.metadata.input_size**2 + self.metadata.output_dim)
        return max(1, min(MAX_CHUNK, MEMORY_BUDGET_BYTES // per_crop))

    def crops(self, image: np.ndarray, boxes: Sequence[Sequence[float]]) -> np.ndarray:
        """The network input ``(N, 1, S, S)`` for boxes in an image (the shared crop)."""
        _check_box_count(boxes)
        return crop_batch(image, boxes, self.metadata.input_size, self.metadata.crop_padding)

    def _object_ids(self, count: int, obj_ids: Sequence[int] | None) -> list[int | None]:
        """The object of each box; unknown (None) for a model of several objects when not given."""
        known = sorted(self.metadata.objects)
        if obj_ids is None:
            return [known[0] if len(known) == 1 else None] * count
        if isinstance(obj_ids, (str, bytes)) or not isinstance(obj_ids, (Sequence, np.ndarray)):
            raise PopcodeError(f"obj_ids must be a list of integers, got {type(obj_ids).__name__}")
        if len(obj_ids) != count:
            raise PopcodeError(f"got {len(obj_ids)} object ids for {count} boxes")
        ids = [integer(i, "an object id") for i in obj_ids]
        unknown = sorted(set(ids) - set(known))
        if unknown:
            raise PopcodeError(f"object ids {unknown} are not in this model (it knows {known})")
        return ids

    def predict(
        self,
        image: np.ndarray,
        boxes: Sequence[Sequence[float]],
        K: Sequence[float] | np.ndarray | None = None,
        return_code: bool = False,
        obj_ids: Sequence[int] | None = None,
        top_k: int = 1,
        translation: bool = False,
        depth: np.ndarray | None = None,
        depth_scale: float = 1.0,
        refine_depth: bool = False,
    ) -> list[Prediction]:
        """Rotations of the objects in ``boxes`` (``(x, y, w, h)`` pixels) of ``image``.

        ``image`` is grey ``(H, W)`` or RGB ``(H, W, 3)``, uint8/uint16 or float
        in [0, 1]. ``K`` (``fx, fy, cx, cy`` or 3x3) is required for models that
        predict allocentric rotations and for ``translation``. ``obj_ids`` names
        the object in each box (needed for models of several objects when
        ``translation`` or ``top_k`` uses the object's extents or symmetries).
        ``top_k > 1`` lists every distinct pose of a population code. Up to
        ``MAX_BOXES_PER_CALL`` boxes, run in chunks of :attr:`chunk_size`.

        ``depth`` ``(H, W)``, registered to the image (mm = value x
        ``depth_scale``, 0: no reading), gives each box its translation from the
        object's observed surface (:mod:`popcode_runtime.depth.surface_fit`; implies ``translation``); an
        instance whose depth is unusable keeps the box's, and its
        ``depth_note`` says why. ``refine_depth`` also refines rotation and
        translation against the observed points (needs ``pip install
        ./runtime[depth]``), from each of the ``top_k`` hypotheses, keeping the
        best fit. Every argument is checked first; bad ones raise :class:`PopcodeError`.
        """
        meta = self.metadata
        return_code, translation = flag(return_code, "return_code"), flag(translation, "translation")
        refine_depth = flag(refine_depth, "refine_depth")
        top_k = integer(top_k, "top_k", 1, MAX_TOP_K)
        if refine_depth and depth is None:
            raise PopcodeError("refine_depth refines the pose against a depth image: pass depth")
        translation = translation or depth is not None
        camera = None
        if K is not None:
            camera = parse_camera_matrix(K)
        elif meta.rotation_frame == RotationFrame.ALLOCENTRIC or translation:
            needs = ("translation from depth" if depth is not None else "translation from the box") if translation \
                else "this model predicts allocentric rotations"
            raise PopcodeError(f"{needs}: pass the camera matrix K")
        if top_k > 1 and meta.representation != Representation.POPULATION_CODE:
            raise PopcodeError(f"hypotheses (top_k > 1) need a population-code model, this one is "
                               f"{meta.representation}")
        if obj_ids is None and len(meta.objects) > 1 and (translation or top_k > 1):
            raise PopcodeError(f"this model knows objects {sorted(meta.objects)}: pass the object id of each box")
        _check_box_count(boxes)
        if return_code and len(boxes) * meta.output_dim * 4 > MEMORY_BUDGET_BYTES:
            raise PopcodeError(f"returning the codes of {len(boxes)} boxes exceeds the memory budget of "
                               f"{MEMORY_BUDGET_BYTES >> 20} MiB; ask for fewer boxes at a time")
        ids = self._object_ids(len(boxes), obj_ids)
        image = check_image(image)
        depth_mm = None
        if depth is not None:
            depth_mm = check_depth(depth, image.shape, depth_scale)
            for obj_id in sorted(set(ids)):
                self.object_surface(obj_id)
            if refine_depth:
                require_small_gicp()
        request = _Request(camera, return_code, top_k, translation, depth_mm, refine_depth)
        timings = np.zeros(4)
        predictions: list[Prediction] = []
        for start in range(0, len(boxes), self.chunk_size):
            chunk = range(start, min(start + self.chunk_size, len(boxes)))
            predictions += self._predict_chunk(image, [boxes[i] for i in chunk], [ids[i] for i in chunk], request,
                                               timings)
        self.last_timings = Timings(*(float(t) for t in timings))
        return predictions

    def object_surface(self, obj_id: int | None) -> ObjectSurface:
        """The surface points that depth needs of an object; a model exported without them is told in one line."""
        surface = self._surfaces.get(obj_id) if obj_id is not None else None
        if surface is None:
            raise PopcodeError(f"this model carries no surface points for object {obj_id}, which depth needs: "
                               "export it again with this version's popcode-train")
        return surface

    def _predict_chunk(self, image: np.ndarray, boxes: list, ids: list[int | None], request: _Request,
                       timings: np.ndarray) -> list[Prediction]:
        """Crop, run, decode and convert one chunk of boxes; adds its stage times to ``timings``."""
        meta, camera = self.metadata, request.camera
        started = time.perf_counter()
        crops = crop_batch(image, boxes, meta.input_size, meta.crop_padding)
        cropped = time.perf_counter()
        output = self.run(crops)
        inferred = time.perf_counter()
        decoded = decode_output(output, meta, self.decoder)
        confidence = self._confidence(output, ids)
        to_camera = self._to_camera_frame(boxes, camera)
        R = to_camera(decoded.R, slice(None))
        axes, angles = matrix_to_axis_angle(R)
        predictions = []
        depth_s = 0.0
        for i, box in enumerate(boxes):
            info = meta.objects.get(ids[i], {})
            hypotheses = None
            if request.top_k > 1:
                found = find_hypotheses(PopulationCode(meta.code), output[i], self._symmetry_rotations(ids[i]),
                                        top_k=request.top_k, refine=self.decoder == "refined")
                hypotheses = [replace(h, R_m2c=to_camera(h.R_m2c, i), equivalent=to_camera(h.equivalent, i))
                              for h in found]
            prediction = Prediction(
                R_m2c=R[i], axis=axes[i], angle_rad=float(angles[i]), score=float(decoded.activation[i]),
                box=tuple(float(v) for v in box), obj_id=ids[i], code=output[i].copy() if request.return_code else None,
                hypotheses=hypotheses, confidence=confidence[i],
            )
            if request.depth_mm is not None:
                placed = time.perf_counter()
                prediction = self._with_depth(prediction, request, info)
                depth_s += time.perf_counter() - placed
            elif request.translation:
                prediction = replace(prediction, t_m2c_mm=translation_from_box(R[i], box, camera,
                                                                               object_points_mm(info)),
                                     t_source=TranslationSource.BOX)
            predictions.append(prediction)
        timings += (cropped - started, inferred - cropped, time.perf_counter() - inferred - depth_s, depth_s)
        return predictions

    def _with_depth(self, prediction: Prediction, request: _Request, info: dict) -> Prediction:
        """The prediction placed with the depth image (and refined against it when asked)."""
        starts = [prediction.R_m2c] + [h.R_m2c for h in (prediction.hypotheses or [])[1:]]
        pose = pose_with_depth(starts, prediction.box, request.camera, request.depth_mm,
                               self.object_surface(prediction.obj_id), object_points_mm(info), info,
                               request.refine_depth)
        axis, angle = matrix_to_axis_angle(pose.R_m2c)
        return replace(prediction, R_m2c=pose.R_m2c, axis=axis, angle_rad=float(angle), t_m2c_mm=pose.t_m2c_mm,
                       t_source=pose.source, depth_fit=pose.fit, depth_note=pose.note)

    def _confidence(self, output: np.ndarray, ids: list[int | None]) -> list[float | None]:
        """The calibrated confidence of each output; None without a calibrator or when the object is not known
        (the features need its symmetries)."""
        calibrator, meta = self.metadata.confidence, self.metadata
        confidence: list[float | None] = [None] * len(output)
        if calibrator is None:
            return confidence
        for obj_id in {i for i in ids if i is not None}:
            rows = [row for row, i in enumerate(ids) if i == obj_id]
            features = code_features(meta.code, output[rows], self._symmetries[obj_id], calibrator.rival_radius_deg)
            for row, value in zip(rows, calibrator.probability(features, self.decoder), strict=True):
                confidence[row] = float(value)
        return confidence

    def _symmetry_rotations(self, obj_id: int | None) -> np.ndarray:
        """The object's symmetry rotations (identity alone for an object not named)."""
        return self._symmetries[obj_id] if obj_id is not None else np.eye(3)[None]

    def _to_camera_frame(self, boxes: Sequence[Sequence[float]], camera: np.ndarray | None):
        """A function ``(R, which_boxes) -> R`` in the camera frame (identity for egocentric models)."""
        if self.metadata.rotation_frame != RotationFrame.ALLOCENTRIC:
            return lambda R, _which: R
        centres = np.stack([box_centre(box) for box in boxes])
        return lambda R, which: allocentric_to_egocentric(R, camera, centres[which])


@dataclass(frozen=True)
class _Request:
    """What one :meth:`PoseEstimator.predict` call asks for, checked."""

    camera: np.ndarray | None
    return_code: bool
    top_k: int
    translation: bool
    depth_mm: np.ndarray | None  # (H, W) float32 mm, 0: no reading
    refine_depth: bool


def _check_box_count(boxes: Sequence[Sequence[float]]) -> None:
    if isinstance(boxes, (str, bytes)) or not hasattr(boxes, "__len__") or not hasattr(boxes, "__getitem__"):
        raise PopcodeError(f"boxes must be a list of (x, y, w, h), got {type(boxes).__name__}")
    if len(boxes) == 0:
        raise PopcodeError("no boxes given")
    if len(boxes) > MAX_BOXES_PER_CALL:
        raise PopcodeError(f"{len(boxes)} boxes in one call; the limit is {MAX_BOXES_PER_CALL}")
