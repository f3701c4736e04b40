"""``PoseEstimator``: a popcode model behind one call, image + boxes -> rotations (the one inference pipeline)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..base.errors import PopcodeError
from ..coding.confidence import code_features
from ..coding.hypotheses import find_hypotheses
from ..coding.population_code import PopulationCode
from ..depth.placement import pose_with_depth
from ..depth.surface_fit import ObjectSurface, TranslationSource, object_surface
from ..geometry.crop import box_centre, crop_batch
from ..geometry.rotations import matrix_to_axis_angle, ray_rotation
from ..geometry.symmetries import symmetry_rotations
from ..geometry.translation import object_points_mm, translation_from_box
from ..model.decoding import check_decoder, decode_output
from ..model.engine import Engine, OnnxEngine
from ..model.metadata import ModelMetadata, Representation, RotationFrame
from .prediction import Prediction, Timings
from .request import MEMORY_BUDGET_BYTES, PredictRequest, check_box_count, check_request

MAX_CHUNK = 256  # crops per engine call
# poses of a population code that a depth refinement starts from when fewer hypotheses are asked for: the code's
# first guess in a bin is often a look-alike pose that the depth rules out (gain and cost:
# bench/results/refine-starts.md, issue 65)
REFINE_STARTS = 3


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
        self.last_timings = Timings()
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
        check_box_count(boxes)
        return crop_batch(image, boxes, self.metadata.input_size, self.metadata.crop_padding)

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
        crop_origin: Sequence[float] | None = None,
    ) -> list[Prediction]:
        """Rotations of the objects in ``boxes`` (``(x, y, w, h)`` pixels) of ``image``.

        ``image`` is grey ``(H, W)`` or RGB ``(H, W, 3)``, uint8/uint16 or float
        in [0, 1]. ``K`` (``fx, fy, cx, cy`` or 3x3) is required for models that
        predict allocentric rotations and for ``translation``; it is checked
        against the image (principal point on it, a field of view a camera can
        have). For an image cut from a larger frame, ``K`` is that frame's and
        ``crop_origin`` ``(x, y)`` the image's top-left in it. ``obj_ids`` names
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
        ./runtime[depth]``), from each of a population code's ``top_k``
        hypotheses (at least :data:`REFINE_STARTS`), keeping the best fit.
        Every argument is checked first; bad ones raise :class:`PopcodeError`.
        """
        request = check_request(self.metadata, image, boxes, K=K, return_code=return_code, obj_ids=obj_ids,
                                top_k=top_k, translation=translation, depth=depth, depth_scale=depth_scale,
                                refine_depth=refine_depth, object_surface=self.object_surface,
                                crop_origin=crop_origin)
        timings, predictions = Timings(), []
        for start in range(0, len(boxes), self.chunk_size):
            chunk = range(start, min(start + self.chunk_size, len(boxes)))
            found, spent = self._predict_chunk([boxes[i] for i in chunk], [request.ids[i] for i in chunk], request)
            predictions += found
            timings += spent
        self.last_timings = timings
        return predictions

    def object_surface(self, obj_id: int | None) -> ObjectSurface:
        """The surface points that depth needs of an object; a model exported without them is told in one line."""
        surface = self._surfaces.get(obj_id) if obj_id is not None else None
        if surface is None:
            raise PopcodeError(f"this model carries no surface points for object {obj_id}, which depth needs: "
                               "export it again with this version's popcode-train")
        return surface

    def _predict_chunk(self, boxes: list, ids: list[int | None],
                       request: PredictRequest) -> tuple[list[Prediction], Timings]:
        """Crop, run, decode and convert one chunk of boxes; the predictions and the seconds of each stage."""
        meta, camera = self.metadata, request.camera
        started = time.perf_counter()
        crops = crop_batch(request.image, boxes, meta.input_size, meta.crop_padding)
        cropped = time.perf_counter()
        output = self.run(crops)
        inferred = time.perf_counter()
        decoded = decode_output(output, meta, self.decoder)
        confidence = self._confidence(output, ids)
        rays = self._ray_rotations(boxes, camera)
        R = _in_camera_frame(rays, decoded.R)
        axes, angles = matrix_to_axis_angle(R)
        starts = request.top_k  # hypotheses searched: those asked for, or the refinement's starts
        if request.refine_depth and meta.representation == Representation.POPULATION_CODE:
            starts = max(starts, REFINE_STARTS)
        predictions = []
        depth_s = 0.0
        for i, box in enumerate(boxes):
            info = meta.objects.get(ids[i], {})
            hypotheses = []
            if starts > 1:
                found = find_hypotheses(PopulationCode(meta.code), output[i], self._symmetry_rotations(ids[i]),
                                        top_k=starts, refine=self.decoder == "refined")
                ray = None if rays is None else rays[i]
                hypotheses = [replace(h, R_m2c=_in_camera_frame(ray, h.R_m2c),
                                      equivalent=_in_camera_frame(ray, h.equivalent)) for h in found]
            prediction = Prediction(
                R_m2c=R[i], axis=axes[i], angle_rad=float(angles[i]), score=float(decoded.activation[i]),
                box=tuple(float(v) for v in box), obj_id=ids[i], code=output[i].copy() if request.return_code else None,
                hypotheses=hypotheses[:request.top_k] if request.top_k > 1 else None, confidence=confidence[i],
            )
            if request.depth_mm is not None:
                placed = time.perf_counter()
                prediction = self._with_depth(prediction, [h.R_m2c for h in hypotheses[1:]], request, info)
                depth_s += time.perf_counter() - placed
            elif request.translation:
                prediction = replace(prediction, t_m2c_mm=translation_from_box(R[i], box, camera,
                                                                               object_points_mm(info)),
                                     t_source=TranslationSource.BOX)
            predictions.append(prediction)
        return predictions, Timings(cropped - started, inferred - cropped, time.perf_counter() - inferred - depth_s,
                                    depth_s)

    def _with_depth(self, prediction: Prediction, other_starts: list[np.ndarray], request: PredictRequest,
                    info: dict) -> Prediction:
        """The prediction placed with the depth image (and refined against it, from its rotation and
        ``other_starts``, when asked)."""
        starts = [prediction.R_m2c, *other_starts]
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

    def _ray_rotations(self, boxes: Sequence[Sequence[float]], camera: np.ndarray | None) -> np.ndarray | None:
        """Per box, ``R_ray`` of the ray through its centre (``(N, 3, 3)``): what takes the rotation its crop shows
        to the camera frame, for allocentric models; None for egocentric ones, whose crops show it already."""
        if self.metadata.rotation_frame != RotationFrame.ALLOCENTRIC:
            return None
        return ray_rotation(camera, np.stack([box_centre(box) for box in boxes]))


def _in_camera_frame(rays: np.ndarray | None, R: np.ndarray) -> np.ndarray:
    """Rotations as the crops show them (``(..., 3, 3)``) in the camera frame: ``R_ego = R_ray R_allo``."""
    return R if rays is None else rays @ np.asarray(R, dtype=np.float64)
