"""The population code's tuning width from the parts' symmetry groups (issue 14).

Every symmetric pose of a part is its own peak in the code. When the tuning
width sigma is wide compared with the distance between two of those peaks, they
merge, and even a perfect network output decodes to a rotation between them
(the hex nut of tests/trainer/test_code_sigma.py at the paper's width on the demo's grid).
The test is empirical: encode the exact code of many rotations, decode it with
the refined decoder (the runtime's, which knows the symmetries) and require the
error up to symmetry to stay below :data:`EXACT_TOLERANCE_DEG`.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.coding.refine import decode_refined
from popcode_runtime.geometry.rotations import random_rotations
from popcode_runtime.geometry.symmetries import rotation_error_up_to_symmetry, symmetry_rotations

CHECK_ROTATIONS = 100  # random rotations per check (seeded: the choice is deterministic)
CHECK_PERCENTILE = 99.0
# "Exact": 1 deg moves a point on the part's surface by < 0.9 % of its diameter, far below the finest
# MSSD threshold (min of metrics.recall.Thresholds.mssd_fractions); merged peaks cost errors of the order
# of their separation.
EXACT_TOLERANCE_DEG = 1.0
SIGMA_STEP_DEG = 2.5  # candidate widths: sigma_deg, sigma_deg - 2.5, ... down to the floor
FLOOR_OF_SPACING = 0.75  # narrower than 3/4 of the grid spacing, the code falls between neurons


def sigma_floor_deg(layout: CodeLayout) -> float:
    """The narrowest width the grid supports: 3/4 of its coarser spacing (axes or angles)."""
    spacing = np.degrees(layout.axis_spacing_rad)
    if not layout.axis_only:
        spacing = max(spacing, 360.0 / layout.n_angles)
    return float(FLOOR_OF_SPACING * spacing)


def exact_decoding_errors_deg(layout: CodeLayout, symmetries: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """Error up to symmetry [deg] of refined-decoding the exact code of each rotation ``(N, 3, 3)``."""
    code = PopulationCode(layout)
    decoded = decode_refined(code, code.encode(rotations, symmetries), symmetries).R
    axis = np.asarray(layout.symmetry_axis) if layout.axis_only else None
    return np.degrees(rotation_error_up_to_symmetry(decoded, rotations, symmetries, axis))


def merged_peaks(layout: CodeLayout, info: Mapping[str, Any]) -> float | None:
    """The exact code's decoding error [deg, 99th percentile] when the part's peaks merge, else None."""
    symmetries = symmetry_rotations(info)
    if len(symmetries) < 2:
        return None
    group = (symmetries.shape, symmetries.dtype.str, symmetries.tobytes())
    try:
        hash(layout)
    except TypeError:  # a layout that cannot be a key (a list for its axis): not remembered
        error = _exact_error_deg.__wrapped__(layout, group, CHECK_ROTATIONS, CHECK_PERCENTILE)
    else:
        error = _exact_error_deg(layout, group, CHECK_ROTATIONS, CHECK_PERCENTILE)
    return error if error > EXACT_TOLERANCE_DEG else None


@functools.lru_cache(maxsize=1024)
def _exact_error_deg(layout: CodeLayout, group: tuple[tuple[int, ...], str, bytes], rotations: int,
                     percentile: float) -> float:
    """:func:`merged_peaks`' error, remembered per layout and symmetry group ``(shape, dtype, bytes)``: choosing
    widths asks for the same ones again for every model of a run (the demo's groups, each model's
    representation, a resumed run)."""
    shape, dtype, data = group
    S = np.frombuffer(data, dtype=dtype).reshape(shape)
    R = random_rotations(rotations, np.random.default_rng(0))
    return float(np.percentile(exact_decoding_errors_deg(layout, S, R), percentile))


def _merge_message(obj_id: int, layout: CodeLayout, error: float) -> str:
    return (f"object {obj_id}: its symmetric poses are closer than the code resolves at sigma "
            f"{layout.sigma_deg:g} deg on the {layout.n_axes} x {layout.n_angles} grid -- even an exact code "
            f"decodes with {error:.1f} deg error (99th percentile)")


def fit_sigma(layout: CodeLayout, objects: Mapping[int, Mapping[str, Any]]) -> CodeLayout:
    """``layout`` with the widest sigma (at most its own) at which no object's symmetric peaks merge.

    Steps down by :data:`SIGMA_STEP_DEG` to :func:`sigma_floor_deg`; if peaks
    still merge there, warns and suggests a finer grid.
    """
    candidates = np.arange(layout.sigma_deg, sigma_floor_deg(layout) - 1e-9, -SIGMA_STEP_DEG)
    if len(candidates) == 0:  # already narrower than the floor: check that width alone
        candidates = np.array([layout.sigma_deg])
    for sigma in candidates:
        candidate = replace(layout, sigma_deg=float(sigma))
        if all(merged_peaks(candidate, info) is None for info in objects.values()):
            return candidate
    narrowest = replace(layout, sigma_deg=float(candidates[-1]))
    warn_merged_peaks(narrowest, objects, hint="a finer grid (more code.n_axes / code.n_angles) resolves them")
    return narrowest


def warn_merged_peaks(layout: CodeLayout, objects: Mapping[int, Mapping[str, Any]], hint: str) -> None:
    """A warning per object whose symmetric peaks merge at ``layout``'s width."""
    for obj_id, info in sorted(objects.items()):
        merged = merged_peaks(layout, info)
        if merged is not None:
            warnings.warn(f"{_merge_message(obj_id, layout, merged)}; {hint}", stacklevel=3)


def checked_sigma(layout: CodeLayout, objects: Mapping[int, Mapping[str, Any]], fit: bool) -> CodeLayout:
    """:func:`fit_sigma` when ``fit``; otherwise ``layout`` unchanged, with a warning where peaks merge."""
    if fit:
        return fit_sigma(layout, objects)
    warn_merged_peaks(layout, objects, hint="set code.sigma_from_symmetries = true or a smaller code.sigma_deg")
    return layout
