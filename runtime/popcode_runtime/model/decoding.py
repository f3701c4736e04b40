"""Network output -> rotations, for every representation a model may export.

The population code and the one-hot baseline share the grid and its argmax
decoder; the single-variable baseline outputs a 6-D rotation (or the symmetry
axis for continuous symmetry); the multiple-hypotheses baseline outputs M
quaternions that are clustered by mean shift.
"""

from __future__ import annotations

import numpy as np

from ..base.errors import PopcodeError
from ..coding.population_code import DecodedRotations, PopulationCode, check_code
from ..coding.refine import decode_refined
from ..geometry.rotations import matrix_to_axis_angle, quaternion_to_matrix, rotation_between, sixd_to_matrix
from .metadata import ModelMetadata, Representation

MEAN_SHIFT_BANDWIDTH_RAD = np.deg2rad(20.0)


def _result(R: np.ndarray, score: np.ndarray) -> DecodedRotations:
    axis, angle = matrix_to_axis_angle(R)
    return DecodedRotations(R=R, axis=axis, angle_rad=angle, neuron=np.full(len(R), -1), activation=score)


def quaternion_mean_shift(quaternions: np.ndarray, bandwidth_rad: float = MEAN_SHIFT_BANDWIDTH_RAD,
                          iterations: int = 20) -> tuple[np.ndarray, float]:
    """Mean shift with a flat kernel on unit quaternions ``(M, 4)`` (``q ~ -q``).

    Returns the mean of the largest cluster and the share of hypotheses in it.
    """
    q = quaternions / np.maximum(np.linalg.norm(quaternions, axis=1, keepdims=True), 1e-12)
    # Rotation angle between q1 and q2 is 2 acos |q1.q2|; within bandwidth <=> |dot| >= cos(bw/2).
    threshold = np.cos(bandwidth_rad / 2.0)
    modes = q.copy()
    for _ in range(iterations):
        dots = modes @ q.T  # (M modes, M points)
        weights = (np.abs(dots) >= threshold) * np.sign(dots)  # align signs to each mode
        shifted = weights @ q
        shifted /= np.maximum(np.linalg.norm(shifted, axis=1, keepdims=True), 1e-12)
        if np.allclose(np.abs(np.sum(shifted * modes, axis=1)), 1.0, atol=1e-9):
            modes = shifted
            break
        modes = shifted
    support = (np.abs(modes @ q.T) >= threshold).sum(axis=1)
    best = int(np.argmax(support))
    return modes[best], float(support[best]) / len(q)


DECODERS = ("argmax", "refined")


def check_decoder(decoder: str, metadata: ModelMetadata | None = None) -> None:
    """Refuse an unknown decoder, or one the model cannot use, when the model is opened, not after predicting."""
    if not isinstance(decoder, str) or decoder not in DECODERS:
        raise PopcodeError(f"unknown decoder {decoder!r}; expected one of {DECODERS}")
    if metadata is not None and decoder == "refined" and metadata.representation != Representation.POPULATION_CODE:
        raise PopcodeError(f"the refined decoder needs a population-code model, this one is "
                           f"{metadata.representation}; use --decoder argmax")


def decode_output(output: np.ndarray, metadata: ModelMetadata, decoder: str = "argmax") -> DecodedRotations:
    """Rotations (in the model's rotation frame) from a batch of outputs ``(N, D)``.

    ``decoder`` is ``argmax`` (the paper's) or ``refined`` (sub-neuron, population codes only).
    """
    check_decoder(decoder, metadata)
    output = check_code(output, metadata.output_dim)
    representation = metadata.representation
    if decoder == "refined":
        return decode_refined(PopulationCode(metadata.code), output)
    if representation in (Representation.POPULATION_CODE, Representation.ONE_HOT):
        return PopulationCode(metadata.code).decode(output)
    if representation == Representation.SINGLE_VARIABLE:
        if metadata.code.axis_only:
            norms = np.linalg.norm(output, axis=1)
            if np.any(norms < 1e-9):
                raise PopcodeError("single-variable axis output is zero; no direction can be decoded")
            R = rotation_between(np.asarray(metadata.code.symmetry_axis), output / norms[:, None])
        else:
            R = sixd_to_matrix(output)
        return _result(R, np.ones(len(output)))
    if representation == Representation.MULTI_HYPOTHESIS:
        quats = output.reshape(len(output), metadata.num_hypotheses, 4)
        means, shares = zip(*(quaternion_mean_shift(q) for q in quats), strict=False)
        return _result(quaternion_to_matrix(np.stack(means)), np.asarray(shares))
    raise PopcodeError(f"no decoder for representation {representation!r}")
