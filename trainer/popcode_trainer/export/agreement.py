"""How closely one model's outputs follow another's on the same crops: argmax and pose agreement."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.hypotheses import argmax_tolerance_rad, same_pose
from popcode_runtime.geometry.symmetries import symmetry_rotations
from popcode_runtime.model.decoding import decode_output
from popcode_runtime.model.metadata import ModelMetadata


@dataclass(frozen=True)
class Comparison:
    """How closely one model's outputs follow a reference on the same crops.

    The argmax agreement undercounts for symmetric objects: their code has a
    near-equal peak per equivalent pose, and tiny changes swap which is the
    highest. The pose agreement (:func:`pose_agreement`) counts those crops
    as agreeing; it is None where it cannot be measured (crops of unknown
    objects for a model whose objects differ in symmetry).
    """

    path: Path
    max_abs_diff: float
    argmax_agreement: float  # share of crops with the same argmax, in [0, 1]
    pose_agreement: float | None  # share of crops decoded to the same pose up to symmetry, in [0, 1]


def crop_symmetries(metadata: ModelMetadata, count: int,
                    obj_ids: Sequence[int] | None = None) -> list[np.ndarray] | None:
    """The symmetry rotations ``(K, 3, 3)`` of each of ``count`` crops' objects, from the model's metadata.

    Without ``obj_ids`` the crops may be of any of the model's objects: fine
    when they all share one set of symmetries (a one-object model), else None.
    """
    if obj_ids is None:
        first, *others = (symmetry_rotations(info) for info in metadata.objects.values())
        if any(S.shape != first.shape or not np.allclose(S, first) for S in others):
            return None
        return [first] * count
    ids = [int(i) for i in np.asarray(obj_ids).reshape(-1)]
    if len(ids) != count:
        raise PopcodeError(f"got {len(ids)} object ids for {count} crops")
    unknown = sorted(set(ids) - set(metadata.objects))
    if unknown:
        raise PopcodeError(f"crop object ids {unknown} are not in this model (it knows {sorted(metadata.objects)})")
    by_object = {obj_id: symmetry_rotations(info) for obj_id, info in metadata.objects.items()}
    return [by_object[i] for i in ids]


def pose_agreement(output: np.ndarray, reference: np.ndarray, metadata: ModelMetadata,
                   obj_ids: Sequence[int] | None = None) -> float | None:
    """Share of crops whose two outputs decode to the same pose up to the crop object's symmetries, in [0, 1].

    Both go through the runtime's argmax decoder (``decode_output``); the
    rotations are the same pose when :func:`~popcode_runtime.coding.hypotheses.same_pose`
    holds within :func:`~popcode_runtime.coding.hypotheses.argmax_tolerance_rad` of
    the model's code grid (one grid step per coordinate: what separates the
    argmax decodes of one pose's equivalent peaks). Axis-only codes compare
    the symmetry-axis direction. None when the crops' objects are needed but
    unknown (see :func:`crop_symmetries`).
    """
    symmetries = crop_symmetries(metadata, len(output), obj_ids)
    if symmetries is None:
        return None
    tolerance = argmax_tolerance_rad(metadata.code)
    R_output, R_reference = decode_output(output, metadata).R, decode_output(reference, metadata).R
    same = [same_pose(metadata.code, R_a, R_b, S, tolerance)
            for R_a, R_b, S in zip(R_output, R_reference, symmetries, strict=True)]
    return float(np.mean(same))


def compare(path: Path, output: np.ndarray, reference: np.ndarray, metadata: ModelMetadata,
            obj_ids: Sequence[int] | None = None) -> Comparison:
    """``output`` against ``reference`` (both ``(N, D)``, same crops); ``obj_ids``: each crop's object."""
    return Comparison(path=path, max_abs_diff=float(np.abs(output - reference).max()),
                      argmax_agreement=float(np.mean(output.argmax(1) == reference.argmax(1))),
                      pose_agreement=pose_agreement(output, reference, metadata, obj_ids))
