"""Trained models behind one call for evaluation: model files -> methods (table rows) -> rotations of split instances.

Every model runs through the runtime's ``PoseEstimator``: an ``.onnx`` file with
onnxruntime (so the shipped runtime is what gets scored), a ``.pt`` checkpoint
with the trainer's torch engine. Several model files may form one method: a
method trained per object group is a model per group, and each instance is
routed to the model that knows its object.
"""

from __future__ import annotations

import warnings
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.inference.image_loop import estimate_images, group_by_image, route_objects
from popcode_runtime.inference.prediction import Prediction
from popcode_runtime.model.decoding import DECODERS, check_decoder
from popcode_runtime.model.metadata import Representation

from ...data.bop import Instance
from ...export.torch_engine import checkpoint_estimator
from .estimates import Estimates
from .results_file import RESULTS_SUFFIX, ResultsMethod, read_results_method
from .translation import object_points

ARGMAX = DECODERS[0]  # the paper's decoder: a method's plain name


@dataclass(frozen=True)
class RotationModel:
    """A model file and the runtime's ``PoseEstimator`` that runs it."""

    path: Path
    estimator: PoseEstimator

    @property
    def objects(self) -> Mapping[int, Mapping[str, Any]]:
        """The model's metadata entry of each object: symmetries, extents, hull points."""
        return self.estimator.metadata.objects

    @property
    def obj_ids(self) -> frozenset[int]:
        return frozenset(self.objects)

    @property
    def confidence_threshold_deg(self) -> float | None:
        """The error threshold the model's calibrated confidence is about; None without a calibrator."""
        calibrator = self.estimator.metadata.confidence
        return None if calibrator is None else calibrator.threshold_deg

    def with_decoder(self, decoder: str) -> RotationModel:
        """The same model (its engine shared) decoded by ``decoder``; itself where it already is."""
        if decoder == self.estimator.decoder:
            return self
        return RotationModel(self.path, PoseEstimator.from_engine(self.estimator.engine, self.estimator.metadata,
                                                                  decoder))


def load_model(path: str | Path, decoder: str = ARGMAX, threads: int = 0) -> RotationModel:
    """A ``.pt`` checkpoint (run by torch) or an ``.onnx`` model (run by onnxruntime with ``threads`` intra-op
    threads, 0: all cores), by file suffix."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"model file not found: {path}")
    if path.suffix not in (".onnx", ".pt"):
        raise PopcodeError(f"{path}: a model is a training checkpoint (.pt) or an ONNX file (.onnx); results "
                           f"are a BOP19 results file ({RESULTS_SUFFIX})")
    try:  # every model is opened, and its decoder checked, before the first prediction
        if path.suffix == ".onnx":
            return RotationModel(path, PoseEstimator(path, threads=threads, decoder=decoder))
        return RotationModel(path, checkpoint_estimator(path, decoder))
    except PopcodeError as error:
        if str(path) in str(error):
            raise
        raise PopcodeError(f"{path}: {error}") from error


@dataclass(frozen=True)
class Method:
    """One row of the tables: a name and the models that together cover its objects."""

    name: str
    models: tuple[RotationModel, ...]

    def object_points(self) -> dict[int, np.ndarray]:
        """Object id -> the points its model's metadata gives the runtime to fit a box."""
        points_mm: dict[int, np.ndarray] = {}
        for model in self.models:
            try:
                points_mm.update(object_points(model.objects))
            except PopcodeError as error:
                raise PopcodeError(f"{model.path}: no points to fit a box to: {error}") from error
        return points_mm

    @property
    def paths(self) -> tuple[str, ...]:
        return tuple(str(model.path) for model in self.models)

    @property
    def confidence_thresholds_deg(self) -> set[float | None]:
        """The threshold of each model's calibrated confidence (None for a model without a calibrator)."""
        return {model.confidence_threshold_deg for model in self.models}

    @property
    def estimators(self) -> list[PoseEstimator]:
        return [model.estimator for model in self.models]

    @property
    def decoder(self) -> str:
        """How the method's models turn their output into a rotation (one decoder for all: :meth:`with_decoder`)."""
        return self.models[0].estimator.decoder

    def accepts_decoder(self, decoder: str) -> bool:
        """Whether every model of the method can be decoded by ``decoder``."""
        try:
            for estimator in self.estimators:
                check_decoder(decoder, estimator.metadata)
        except PopcodeError:
            return False
        return True

    def with_decoder(self, decoder: str, name: str) -> Method:
        """The same models (their engines shared, not reopened) decoded by ``decoder``, as method ``name``."""
        return Method(name, tuple(model.with_decoder(decoder) for model in self.models))

    @property
    def population_code(self) -> bool:
        """Whether every model of the method outputs a population code (and so can list hypotheses)."""
        return all(e.metadata.representation == Representation.POPULATION_CODE for e in self.estimators)

    def known_objects(self) -> set[int]:
        """The objects the method's models estimate; two models for one object is an error."""
        try:
            return set(route_objects(self.estimators, self.paths))
        except PopcodeError as error:
            raise PopcodeError(f"method {self.name!r}: {error}") from error

    def estimate(self, instances: Sequence[Instance], models_info: Mapping[int, Mapping[str, Any]],
                 progress: bool = True, top_k: int = 1) -> Estimates:
        """Run the models on every instance (``models_info`` is not needed: the models carry their objects);
        ``top_k > 1`` also lists the hypotheses of population codes (none for other representations)."""
        return predict_rotations(self, instances, progress, top_k if self.population_code else 1)


def predict_rotations(method: Method, instances: Sequence[Instance], progress: bool = True,
                      top_k: int = 1) -> Estimates:
    """The method's estimate of every instance, through the runtime's per-image loop (each image read once).

    ``top_k > 1`` (population codes only) adds each instance's ``top_k`` candidate
    rotations (:attr:`Estimates.hypotheses`). The seconds per crop, and each
    image's seconds (:attr:`Estimates.image_s`, the sum over its crops), count the
    models' predict calls only, not reading the images (with hypotheses, their search too).
    """
    known = method.known_objects()
    missing = sorted({inst.obj_id for inst in instances} - known)
    if missing:
        raise PopcodeError(f"method {method.name!r} has no model for objects {missing} of the split "
                           f"(its models know {sorted(known)}); pass --obj-ids to evaluate fewer objects")
    images = group_by_image(instances)
    R_est, confidence, score = np.empty((len(instances), 3, 3)), np.empty(len(instances)), np.empty(len(instances))
    image_s = np.empty(len(instances))
    hypotheses = np.empty((top_k, len(instances), 3, 3)) if top_k > 1 else None
    options = {"top_k": top_k} if top_k > 1 else {}
    predict_s = 0.0
    for done in tqdm(estimate_images(method.estimators, method.paths, images, **options), total=len(images),
                     desc=f"predict {method.name}", unit="img", disable=not progress):
        rows = list(done.key)
        R_est[rows], confidence[rows], score[rows] = _arrays(done.predictions)
        image_s[rows] = done.predict_s  # all of the image's crops: BOP19's time, on every row of the image
        if hypotheses is not None:
            hypotheses[:, rows] = np.stack([ranked_rotations(p, top_k) for p in done.predictions], axis=1)
        predict_s += done.predict_s
    return Estimates(R_est, confidence, score, predict_s / max(len(instances), 1), image_s, hypotheses)


def ranked_rotations(prediction: Prediction, top_k: int) -> np.ndarray:
    """``(top_k, 3, 3)``: the prediction's own rotation, then its other hypotheses strongest first, padded with
    the first (so that the best of the top 1 is always the plain estimate)."""
    ranked = [prediction.R_m2c] + [h.R_m2c for h in (prediction.hypotheses or [])[1:top_k]]
    return np.stack(ranked + [prediction.R_m2c] * (top_k - len(ranked)))


def _arrays(predictions: Sequence[Prediction]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotations ``(n, 3, 3)`` in the camera frame, their calibrated confidence (NaN: none) and raw score."""
    confidence = [np.nan if p.confidence is None else p.confidence for p in predictions]
    return np.stack([p.R_m2c for p in predictions]), np.array(confidence), np.array([p.score for p in predictions])


def decoder_method_name(name: str, decoder: str) -> str:
    """The table row of method ``name`` decoded by ``decoder``: the name itself for the paper's argmax, else
    ``NAME (decoder)``, e.g. ``population_code (refined)``."""
    return name if decoder == ARGMAX else f"{name} ({decoder})"


def _decoder_list(decoders: str | Sequence[str]) -> tuple[str, ...]:
    """The decoders asked for, each once, in order; each is known (refused now, not after the first model)."""
    listed = (decoders,) if isinstance(decoders, str) else tuple(dict.fromkeys(decoders))
    if not listed:
        raise PopcodeError(f"no decoder given; choose one or more of {DECODERS}")
    for decoder in listed:
        check_decoder(decoder)
    return listed


def methods_from_paths(paths: Sequence[str | Path], names: Sequence[str] | None = None,
                       decoders: str | Sequence[str] = ARGMAX, threads: int = 0) -> list[Method | ResultsMethod]:
    """Methods from model files and BOP19 results files (``.csv``); model files given the same name form one
    method (one table row), a results file is a method of its own.

    Without names each file is its own method, named after the file. With
    several ``decoders`` each method of population codes becomes one method
    per decoder, named by :func:`decoder_method_name`, in the order given (the
    models are opened once); a method that cannot use a decoder (any but
    argmax for other representations; a results file has no decoder) is kept
    once, with one warning for all such. A single decoder keeps the plain name. ``threads``: onnxruntime's
    intra-op threads for ONNX models (0: all cores).
    """
    decoders = _decoder_list(decoders)
    if names and len(names) != len(paths):
        raise PopcodeError(f"{len(names)} names for {len(paths)} models: give one --name per model, or none")
    opened_with = decoders[0] if len(decoders) == 1 else ARGMAX  # argmax: every model can; then one per decoder
    grouped: dict[str, list[RotationModel]] = {}
    results: dict[str, ResultsMethod] = {}
    for index, path in enumerate(paths):
        name = names[index] if names else Path(path).stem
        if Path(path).suffix == RESULTS_SUFFIX:
            if name in results or name in grouped:
                raise PopcodeError(f"{path}: a results file is a method of its own; give it a name no other file has")
            results[name] = read_results_method(Path(path), name)
        elif name in results:
            raise PopcodeError(f"{path}: the name {name!r} is a results file's; give the model another")
        else:
            grouped.setdefault(name, []).append(load_model(path, opened_with, threads))
    methods = {name: Method(name, tuple(models)) for name, models in grouped.items()} | results
    ordered = [methods[name] for name in dict.fromkeys(names or [Path(p).stem for p in paths])]
    return ordered if len(decoders) == 1 else _per_decoder(ordered, decoders)


def _per_decoder(methods: Sequence[Method | ResultsMethod], decoders: Sequence[str]) -> list[Method | ResultsMethod]:
    """Each method once per decoder it can use (see :func:`methods_from_paths`)."""
    expanded: list[Method | ResultsMethod] = []
    once: list[str] = []
    for method in methods:
        if isinstance(method, ResultsMethod):
            expanded.append(method)
            once.append(f"{method.name!r} (a results file)")
            continue
        usable = [decoder for decoder in decoders if method.accepts_decoder(decoder)]
        if len(usable) < len(decoders):
            representations = sorted({str(estimator.metadata.representation) for estimator in method.estimators})
            once.append(f"{method.name!r} ({', '.join(representations)})")
        expanded += [method.with_decoder(d, decoder_method_name(method.name, d)) for d in usable] or [method]
    repeated = sorted(name for name, count in Counter(m.name for m in expanded).items() if count > 1)
    if repeated:
        raise PopcodeError(f"with --decoder {' '.join(decoders)} two methods would be named {repeated[0]!r}; "
                           "give the models other names")
    if once:
        skipped = [d for d in decoders if d != ARGMAX]
        warnings.warn(f"decoder {', '.join(skipped)} applies to population-code models only; scored once: "
                      f"{', '.join(once)}", stacklevel=3)
    return expanded

