"""The code's width from the symmetry group: symmetric peaks of a perfect code must not merge."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from symmetry_cases import BASE, CASES, _flat

from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.coding.refine import decode_refined
from popcode_runtime.geometry.rotations import random_rotations
from popcode_runtime.geometry.symmetries import rotation_error_up_to_symmetry, symmetry_rotations
from popcode_trainer.train import code_sigma
from popcode_trainer.train.code_sigma import exact_decoding_errors_deg, fit_sigma, merged_peaks, sigma_floor_deg
from popcode_trainer.train.representations import build_representation

DEMO_GRID = dict(n_axes=642, n_angles=36)
# A hex nut: 6-fold about its axis and upside-down, 12 equivalent poses.
HEX_NUT = {**BASE, "symmetries_discrete": [_flat([0, 0, 1], k * np.pi / 3) for k in range(1, 6)]
           + [_flat([np.cos(k * np.pi / 6), np.sin(k * np.pi / 6), 0], np.pi) for k in range(6)]}
# Twelve-fold about one axis: equivalent poses 30 deg apart.
TWELVE_FOLD = {**BASE, "symmetries_discrete": [_flat([0, 0, 1], k * np.pi / 6) for k in range(1, 12)]}


def test_the_hex_nut_has_twelve_poses() -> None:
    S = symmetry_rotations(HEX_NUT)
    assert len(S) == 12
    products = np.einsum("aij,bjk->abik", S, S).reshape(-1, 3, 3)  # a group: closed under composition
    assert np.all(rotation_error_up_to_symmetry(products, np.broadcast_to(np.eye(3), products.shape), S) < 1e-6)


def test_a_layout_and_group_are_decoded_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """Choosing widths asks the same question for every model of a run: it is answered once per layout and
    symmetry group (widths no other test asks about, so the first answer is computed here)."""
    layout = CodeLayout(sigma_deg=27.3, n_axes=162, n_angles=24)
    first = merged_peaks(layout, HEX_NUT)

    def no_second_decode(*args: object) -> None:
        raise AssertionError("decoded again")

    monkeypatch.setattr(code_sigma, "exact_decoding_errors_deg", no_second_decode)
    assert merged_peaks(layout, {**HEX_NUT, "diameter": 99.0}) == first  # the same group: remembered
    with pytest.raises(AssertionError, match="decoded again"):
        merged_peaks(replace(layout, sigma_deg=26.1), HEX_NUT)
    with pytest.raises(AssertionError, match="decoded again"):
        merged_peaks(layout, TWELVE_FOLD)


def test_paper_width_merges_the_hex_nut_peaks_and_warns() -> None:
    layout = CodeLayout(sigma_deg=20.0, **DEMO_GRID)
    merged = merged_peaks(layout, HEX_NUT)
    assert merged is not None and merged > 10.0  # decoded between the peaks, not at one
    with pytest.warns(UserWarning, match="object 7: its symmetric poses are closer than the code resolves"):
        rep = build_representation("population_code", {7: HEX_NUT}, sigma_deg=20.0, **DEMO_GRID)
    assert rep.layout.sigma_deg == 20.0  # kept as configured


def test_fitted_width_decodes_every_hex_nut_pose_exactly() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a width that resolves the peaks exists on this grid: no warning
        rep = build_representation("population_code", {7: HEX_NUT}, sigma_deg=20.0, sigma_from_symmetries=True,
                                   **DEMO_GRID)
    layout = rep.layout
    assert sigma_floor_deg(layout) <= layout.sigma_deg < 20.0
    assert merged_peaks(layout, HEX_NUT) is None
    rotations = random_rotations(50, np.random.default_rng(5))  # not the rotations the check used
    S = symmetry_rotations(HEX_NUT)
    code = PopulationCode(layout)
    refined = decode_refined(code, code.encode(rotations, S), S).R
    assert np.degrees(rotation_error_up_to_symmetry(refined, rotations, S)).max() < 1.0
    argmax = code.decode(code.encode(rotations, S)).R  # the grid's resolution, as with no symmetry
    plain = code.decode(code.encode(rotations)).R
    assert (np.degrees(rotation_error_up_to_symmetry(argmax, rotations, S)).max()
            <= np.degrees(rotation_error_up_to_symmetry(plain, rotations, np.eye(3)[None])).max() + 1e-6)
    wider = CodeLayout(sigma_deg=layout.sigma_deg + 2.5, **DEMO_GRID)  # the widest such width was chosen
    assert merged_peaks(wider, HEX_NUT) is not None


def test_twelve_fold_part_needs_a_finer_grid() -> None:
    coarse = CodeLayout(sigma_deg=20.0, **DEMO_GRID)
    with pytest.warns(UserWarning, match="object 3: .* a finer grid"):
        narrowest = fit_sigma(coarse, {3: TWELVE_FOLD})
    assert narrowest.sigma_deg == pytest.approx(sigma_floor_deg(coarse), abs=2.5)
    assert merged_peaks(narrowest, TWELVE_FOLD) is not None
    fine = fit_sigma(CodeLayout(sigma_deg=7.5, n_axes=2562, n_angles=72), {3: TWELVE_FOLD})  # 30 deg apart
    assert fine.sigma_deg < 7.5 and merged_peaks(fine, TWELVE_FOLD) is None
    rotations = random_rotations(30, np.random.default_rng(1))
    assert np.median(exact_decoding_errors_deg(fine, symmetry_rotations(TWELVE_FOLD), rotations)) < 0.5


@pytest.mark.parametrize("case", ["none", "two_fold", "continuous_flip"])
def test_parts_whose_peaks_stay_apart_keep_the_configured_width(case: str) -> None:
    rep = build_representation("population_code", {1: CASES[case]}, sigma_deg=20.0, sigma_from_symmetries=True,
                               **DEMO_GRID)
    assert rep.layout.sigma_deg == 20.0


def test_pooled_parts_share_the_narrowest_width() -> None:
    alone = build_representation("population_code", {7: HEX_NUT}, sigma_deg=20.0, sigma_from_symmetries=True,
                                 **DEMO_GRID)
    pooled = build_representation("population_code", {1: CASES["none"], 7: HEX_NUT}, sigma_deg=20.0,
                                  sigma_from_symmetries=True, **DEMO_GRID)
    assert pooled.layout.sigma_deg == alone.layout.sigma_deg


def test_baselines_do_not_check_the_width() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rep = build_representation("single_variable", {7: HEX_NUT}, sigma_deg=20.0, **DEMO_GRID)
    assert rep.layout.sigma_deg == 20.0
