"""Output representations: what the network predicts, its target, its loss and its decoding.

The population code is the paper's method; single variable, one-hot and
multiple hypotheses are the baselines of section IV-C, trained with the same
network and data. Targets are numpy (built in data-loader workers), losses are
torch, and decoding is the runtime's :func:`popcode_runtime.model.decoding.decode_output`,
so a trained model decodes in training exactly as it will in the runtime.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Protocol

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812 (the usual torch alias)

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.population_code import CodeLayout, DecodedRotations, PopulationCode
from popcode_runtime.geometry.crop import box_centre
from popcode_runtime.geometry.rotations import (
    egocentric_to_allocentric,
    matrix_to_quaternion,
    matrix_to_sixd,
)
from popcode_runtime.geometry.symmetries import (
    SymmetryClass,
    continuous_axis,
    rotation_error_up_to_symmetry,
    symmetry_class,
    symmetry_rotations,
)
from popcode_runtime.model.decoding import decode_output
from popcode_runtime.model.metadata import ModelMetadata, Representation, RotationFrame

from .code_sigma import checked_sigma

EPSILON_START = 0.05  # eq. 3: weight of the average loss, annealed linearly over training
EPSILON_END = 0.01


class InstanceLike(Protocol):
    """The fields of ``popcode_trainer.data.bop.Instance`` a target needs."""

    obj_id: int
    R_m2c: np.ndarray
    K: np.ndarray
    box: tuple[float, float, float, float]


def code_layout(objects: Mapping[int, Mapping[str, Any]], n_axes: int, n_angles: int, sigma_deg: float) -> CodeLayout:
    """The one code layout the pooled ``objects`` can share; refuses sets that cannot share one.

    Objects with a continuous symmetry use the axis-only code, the others the
    full code, so the two kinds cannot be pooled; pooled continuous objects
    must share the symmetry axis, because the code (and its decoder) knows one.
    """
    if not objects:
        raise PopcodeError("no objects to train on")
    continuous = sorted(k for k, info in objects.items() if symmetry_class(info) == SymmetryClass.CONTINUOUS)
    if not continuous:
        return CodeLayout(n_axes=n_axes, n_angles=n_angles, sigma_deg=sigma_deg)
    others = sorted(set(objects) - set(continuous))
    if others:
        raise PopcodeError(
            f"objects {continuous} have a continuous symmetry (axis-only code) and objects {others} do not "
            f"(full code); they cannot share one model -- train them separately, e.g. --set "
            f"data.obj_ids='{continuous}' for one model and --set data.obj_ids='{others}' for the other"
        )
    axis = continuous_axis(objects[continuous[0]])
    for obj_id in continuous[1:]:
        if abs(abs(float(axis @ continuous_axis(objects[obj_id]))) - 1.0) > 1e-6:
            raise PopcodeError(
                f"objects {continuous[0]} and {obj_id} have continuous symmetries about different model axes; "
                f"one axis-only code encodes one axis -- train them separately (--set data.obj_ids='[{obj_id}]')"
            )
    return CodeLayout(n_axes=n_axes, n_angles=n_angles, sigma_deg=sigma_deg, axis_only=True,
                      symmetry_axis=tuple(axis))


class OutputRepresentation:
    """Base of the four representations: frames, metadata, decoding and the error up to symmetry."""

    name: ClassVar[str]

    def __init__(self, objects: Mapping[int, Mapping[str, Any]], layout: CodeLayout,
                 rotation_frame: str = RotationFrame.EGOCENTRIC, num_hypotheses: int = 0) -> None:
        self.objects = {int(k): dict(v) for k, v in objects.items()}
        self.metadata = ModelMetadata(representation=self.name, code=layout, objects=self.objects,
                                      rotation_frame=rotation_frame, num_hypotheses=num_hypotheses)
        self.layout = layout
        self._symmetries = {k: symmetry_rotations(info) for k, info in self.objects.items()}

    @property
    def output_dim(self) -> int:
        return self.metadata.output_dim

    def frame_rotation(self, R_m2c: np.ndarray, K: np.ndarray | None = None,
                       box: tuple[float, float, float, float] | None = None) -> np.ndarray:
        """The rotation the model predicts: ``R_m2c`` itself, or as seen along the ray to the box centre."""
        if self.metadata.rotation_frame == RotationFrame.EGOCENTRIC:
            return np.asarray(R_m2c, dtype=np.float64)
        if K is None or box is None:
            raise PopcodeError("allocentric targets need the camera matrix K and the box of each instance")
        return egocentric_to_allocentric(R_m2c, K, box_centre(box))

    def symmetries(self, obj_id: int) -> np.ndarray:
        if obj_id not in self._symmetries:
            raise PopcodeError(f"object {obj_id} is not one of this model's objects {sorted(self._symmetries)}")
        return self._symmetries[obj_id]

    def target(self, instance: InstanceLike) -> np.ndarray:
        """float32 target of one instance."""
        return self.targets([instance])[0]

    def targets(self, instances: Sequence[InstanceLike]) -> np.ndarray:
        """float32 targets ``(B, D)`` of a batch (the data set's ``targets_fn``): one call per object."""
        R = np.stack([self.frame_rotation(inst.R_m2c, inst.K, inst.box) for inst in instances])
        obj_ids = np.array([int(inst.obj_id) for inst in instances])
        targets: np.ndarray | None = None
        for obj_id in np.unique(obj_ids):
            rows = np.flatnonzero(obj_ids == obj_id)
            part = self.targets_from_rotations(R[rows], int(obj_id))
            if targets is None:
                targets = np.empty((len(instances), part.shape[1]), dtype=np.float32)
            targets[rows] = part
        assert targets is not None  # instances is not empty
        return targets

    def targets_from_rotations(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        """Targets ``(n, D)`` of rotations ``(n, 3, 3)`` of one object; vectorised where it pays."""
        return np.stack([self.target_from_rotation(r, obj_id) for r in R])

    def target_from_rotation(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        raise NotImplementedError

    def loss(self, output: torch.Tensor, target: torch.Tensor, progress: float) -> torch.Tensor:
        """Mean loss of a batch; ``progress`` in [0, 1] is the share of training done."""
        raise NotImplementedError

    def decode(self, output: np.ndarray) -> DecodedRotations:
        """Rotations in the model's frame, decoded exactly as the runtime does."""
        return decode_output(np.asarray(output, dtype=np.float32), self.metadata)

    def errors_rad(self, R_pred: np.ndarray, R_true: np.ndarray, obj_ids: np.ndarray) -> np.ndarray:
        """Rotation error ``(N,)`` [rad] up to symmetry, both rotations in the same frame.

        Discrete symmetries: min over ``S`` of angle(R_pred, R_true S). A
        continuous symmetry leaves only the symmetry axis defined, so the error
        is the angle between the predicted and the true axis (min over the
        discrete symmetries, which may flip it).
        """
        errors = np.empty(len(R_pred))
        axis = np.asarray(self.layout.symmetry_axis) if self.layout.axis_only else None
        for obj_id in np.unique(obj_ids):
            rows = np.flatnonzero(obj_ids == obj_id)
            errors[rows] = rotation_error_up_to_symmetry(R_pred[rows], R_true[rows], self.symmetries(int(obj_id)),
                                                         axis)
        return errors


LOSSES = ("mse", "cross_entropy", "mse+cross_entropy")
# Weight of the cross-entropy term in "mse+cross_entropy"; chosen on a validation split from 0.01 and 0.1
# (bench/results/recipe.md). MSE averages over every neuron, most of them zero, so its gradient on a
# peak neuron of a 642 x 36 code starts about 50x smaller than cross entropy's.
HYBRID_CE_WEIGHT = 0.1


def code_mass(layout: CodeLayout) -> float:
    """Sum of the code of one rotation of a part without symmetry (both twin peaks)."""
    return float(PopulationCode(layout).encode(np.eye(3)).sum())


class CodeSoftmax(torch.nn.Module):
    """Logits -> code: ``softmax * code_mass``, so a part without symmetry peaks near 1 as its target does.

    Appended to networks trained with the cross-entropy loss when they are
    loaded for export and evaluation; the runtime's decoders then read a code.
    """

    def __init__(self, mass: float) -> None:
        super().__init__()
        self.mass = mass

    def forward(self, logits: torch.Tensor) -> torch.Tensor:
        return torch.softmax(logits, dim=1) * self.mass


def _code_cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cross entropy of the logits' softmax against the code normalised to sum 1 (every crop weighs the same)."""
    share = target / target.sum(dim=1, keepdim=True).clamp_min(1e-12)
    return -(share * F.log_softmax(logits, dim=1)).sum(dim=1).mean()


class PopulationCodeRepresentation(OutputRepresentation):
    """The paper's method: every symmetric pose a peak of the code.

    ``loss``: ``mse`` (the paper's) on the code; ``cross_entropy`` between the
    output's softmax and the code normalised to sum 1 (each crop weighs the
    same, whatever its number of peaks); or ``mse+cross_entropy``, both on the
    same output, which stays a code (see bench/results/recipe.md).
    """

    name = Representation.POPULATION_CODE

    def __init__(self, *args: Any, loss: str = "mse", **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if loss not in LOSSES:
            raise PopcodeError(f"unknown population-code loss {loss!r}; choose one of {list(LOSSES)}")
        self.loss_kind = loss
        self.code = PopulationCode(self.layout)
        self._logits_to_code = CodeSoftmax(code_mass(self.layout)) if loss == "cross_entropy" else None

    def target_from_rotation(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        return self.targets_from_rotations(R[None], obj_id)[0]

    def targets_from_rotations(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        return self.code.encode(R, self.symmetries(obj_id))

    def loss(self, output: torch.Tensor, target: torch.Tensor, progress: float) -> torch.Tensor:
        if self.loss_kind == "cross_entropy":
            return _code_cross_entropy(output, target)
        if self.loss_kind == "mse+cross_entropy":  # the output stays a code; CE on it as logits ranks the peaks
            return F.mse_loss(output, target) + HYBRID_CE_WEIGHT * _code_cross_entropy(output, target)
        return F.mse_loss(output, target)

    def decode(self, output: np.ndarray) -> DecodedRotations:
        """Logits decode as their code would: the argmax is the same, the activations are the code's."""
        if self._logits_to_code is not None:
            output = self._logits_to_code(torch.as_tensor(output)).numpy()
        return super().decode(output)


class OneHotRepresentation(OutputRepresentation):
    """Baseline: the same grid as a class label, cross entropy.

    The label is the neuron that the population code of the ground truth alone
    (no symmetric copies) peaks at, i.e. the grid rotation nearest to it in
    the code's metric; one label per crop, so symmetric poses are not marked.
    """

    name = Representation.ONE_HOT

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.code = PopulationCode(self.layout)

    def target_from_rotation(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        return self.targets_from_rotations(R[None], obj_id)[0]

    def targets_from_rotations(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        self.symmetries(obj_id)  # refuses an unknown object
        return np.argmax(self.code.encode(R), axis=1)[:, None].astype(np.float64)

    def loss(self, output: torch.Tensor, target: torch.Tensor, progress: float) -> torch.Tensor:
        return F.cross_entropy(output, target[:, 0].long())


class SingleVariableRepresentation(OutputRepresentation):
    """Baseline: the 6-D rotation with the minimum L1 over symmetric targets, or the
    symmetry axis (3-vector, MSE) for objects with a continuous symmetry.

    The target lists every symmetric variant, padded to the largest symmetry
    group among the pooled objects by repeating the first.
    """

    name = Representation.SINGLE_VARIABLE

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._variants = max(len(S) for S in self._symmetries.values())

    def target_from_rotation(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        equivalent = R @ self.symmetries(obj_id)  # (K, 3, 3)
        if self.layout.axis_only:
            variants = equivalent @ np.asarray(self.layout.symmetry_axis)
        else:
            variants = matrix_to_sixd(equivalent)
        padding = np.repeat(variants[:1], self._variants - len(variants), axis=0)
        return np.concatenate([variants, padding]).reshape(-1)

    def loss(self, output: torch.Tensor, target: torch.Tensor, progress: float) -> torch.Tensor:
        variants = target.view(len(target), self._variants, self.output_dim)
        diff = output[:, None] - variants
        per_variant = diff.pow(2).mean(-1) if self.layout.axis_only else diff.abs().mean(-1)
        return per_variant.min(dim=1).values.mean()


class MultiHypothesisRepresentation(OutputRepresentation):
    """Baseline (Manhardt et al.): M quaternions, loss of eq. 3, mean shift at inference.

    The target is the ground-truth quaternion alone: the hypotheses are meant
    to discover symmetric poses by themselves. Distances use ``min(|h - q|,
    |h + q|)`` because ``q`` and ``-q`` are the same rotation.
    """

    name = Representation.MULTI_HYPOTHESIS

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.metadata.num_hypotheses < 2:
            raise PopcodeError("multi_hypothesis needs num_hypotheses >= 2 (eq. 3 divides by M - 1)")

    def target_from_rotation(self, R: np.ndarray, obj_id: int) -> np.ndarray:
        self.symmetries(obj_id)
        return matrix_to_quaternion(R)

    @staticmethod
    def epsilon(progress: float) -> float:
        """eq. 3's epsilon, linear from 0.05 at the start to 0.01 at the end of training."""
        return EPSILON_START + (EPSILON_END - EPSILON_START) * min(max(progress, 0.0), 1.0)

    def loss(self, output: torch.Tensor, target: torch.Tensor, progress: float) -> torch.Tensor:
        M = self.metadata.num_hypotheses
        hypotheses = F.normalize(output.view(len(output), M, 4), dim=-1)
        q = target[:, None]
        squared = torch.minimum((hypotheses - q).pow(2).mean(-1), (hypotheses + q).pow(2).mean(-1))
        weight = self.epsilon(progress) * M / (M - 1)
        return (1.0 - weight) * squared.min(dim=1).values.mean() + weight * squared.mean()


REPRESENTATIONS: dict[str, type[OutputRepresentation]] = {
    cls.name: cls
    for cls in (PopulationCodeRepresentation, OneHotRepresentation, SingleVariableRepresentation,
                MultiHypothesisRepresentation)
}


def build_representation(name: str, objects: Mapping[int, Mapping[str, Any]], n_axes: int, n_angles: int,
                         sigma_deg: float, rotation_frame: str = RotationFrame.EGOCENTRIC,
                         num_hypotheses: int = 0, sigma_from_symmetries: bool = False,
                         loss: str = "mse") -> OutputRepresentation:
    """The representation called ``name`` for the pooled ``objects``; names the valid choices.

    The population code's width is checked against the objects' symmetries
    (:func:`code_sigma.checked_sigma`): narrowed with ``sigma_from_symmetries``,
    otherwise kept with a warning where symmetric peaks merge.
    """
    if name not in REPRESENTATIONS:
        raise PopcodeError(f"unknown representation {name!r}; choose one of {sorted(REPRESENTATIONS)}")
    layout = code_layout(objects, n_axes, n_angles, sigma_deg)
    hypotheses = num_hypotheses if name == Representation.MULTI_HYPOTHESIS else 0
    if name == Representation.POPULATION_CODE:
        layout = checked_sigma(layout, objects, sigma_from_symmetries)
        return PopulationCodeRepresentation(objects, layout, rotation_frame, hypotheses, loss=loss)
    if loss != "mse":
        raise PopcodeError(f"train.loss = {loss!r} applies to the population code; {name} has its own loss")
    return REPRESENTATIONS[name](objects, layout, rotation_frame, hypotheses)


class PerObjectPopulationCodes:
    """One population-code representation per object, for a split whose objects one model cannot
    pool (continuous beside discrete symmetries, see :func:`code_layout`): previews still show each
    object's own target, built exactly as training builds it.
    """

    def __init__(self, objects: Mapping[int, Mapping[str, Any]], n_axes: int, n_angles: int, sigma_deg: float,
                 rotation_frame: str = RotationFrame.EGOCENTRIC) -> None:
        if not objects:
            raise PopcodeError("no objects to build population codes for")
        self.representations = {
            int(obj_id): build_representation(Representation.POPULATION_CODE, {obj_id: info}, n_axes, n_angles,
                                              sigma_deg, rotation_frame)
            for obj_id, info in objects.items()
        }

    def _representation(self, obj_id: int) -> OutputRepresentation:
        if int(obj_id) not in self.representations:
            raise PopcodeError(f"object {obj_id} is not one of the objects {sorted(self.representations)}")
        return self.representations[int(obj_id)]

    def layout(self, obj_id: int) -> CodeLayout:
        """The code layout of object ``obj_id``: axis-only for a continuous symmetry, else full."""
        return self._representation(obj_id).layout

    def target(self, instance: InstanceLike) -> np.ndarray:
        """float32 target of one instance in its object's layout."""
        return self._representation(instance.obj_id).target(instance)

    def targets(self, instances: Sequence[InstanceLike]) -> np.ndarray:
        """Targets ``(B, D)`` of instances whose objects share one layout size (the data set's ``targets_fn``)."""
        return np.stack([self.target(instance) for instance in instances])


def representation_from_metadata(metadata: ModelMetadata) -> OutputRepresentation:
    """Rebuild a representation from a model's (or checkpoint's) metadata."""
    cls = REPRESENTATIONS[metadata.representation]
    return cls(metadata.objects, metadata.code, metadata.rotation_frame, metadata.num_hypotheses)
