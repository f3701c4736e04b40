"""The code each object group of a demo trains with, chosen from its parts' symmetries and stated in one line.

A run's size fixes one grid (axes x angles) and width sigma. Training narrows sigma where a part's
symmetric poses would merge (:mod:`popcode_trainer.train.code_sigma`), but only down to what the grid
resolves; a part with many symmetric poses (a 12-fold nut) needs a finer grid than the demo's. So each
group gets the first grid of :func:`finer_grids` on which, after narrowing, even an exact code decodes
every part within :data:`~popcode_trainer.train.code_sigma.EXACT_TOLERANCE_DEG`, and a sentence saying
what was chosen and why. A group the size's settings resolve keeps them unchanged; a user's group whose parts
need different codes alone is split, one model per code, so that one fine part does not move the rest onto its
grid (:func:`split_by_code`). The built-in demo keeps its sizes' grids (they resolve every built-in part), so
only its test-sized runs narrow sigma alone.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

from popcode_runtime.coding.population_code import CodeLayout
from popcode_runtime.geometry.symmetries import symmetry_rotations

from ..train.code_sigma import fit_sigma, merged_peaks
from ..train.config import CodeConfig
from ..train.representations import code_layout

MAX_NEURONS = 2562 * 72  # the finest grid tried: the paper's axes with 5-degree angles (184 464 outputs)


@dataclass(frozen=True)
class GroupCode:
    """The code settings of one object group's models and the report's sentence about them."""

    obj_ids: tuple[int, ...]
    code: CodeConfig  # what the group trains with (the size's unless they cannot resolve its parts)
    sigma_deg: float  # the width the models will carry, after narrowing
    note: str


def finer_grids(n_axes: int, n_angles: int, axis_only: bool) -> list[tuple[int, int]]:
    """The size's grid, then finer ones up to :data:`MAX_NEURONS`: twice the angles, then four times the axes
    (the next icosphere count: 642 -> 2562), and so on. Axis-only codes have no angles and refine their axes."""
    grids = [(n_axes, n_angles)]
    while True:
        n, m = grids[-1]
        refine_angles = not axis_only and len(grids) % 2 == 1
        finer = (n, 2 * m) if refine_angles else (4 * n - 6, m)
        if finer[0] * (1 if axis_only else finer[1]) > MAX_NEURONS:
            return grids
        grids.append(finer)


def _names(ids: Sequence[int]) -> str:
    return f"object {ids[0]}" if len(ids) == 1 else f"objects {', '.join(map(str, ids))}"


def _layout(code: CodeConfig, objects: Mapping[int, Mapping[str, Any]], grid: tuple[int, int]) -> CodeLayout:
    return code_layout(objects, grid[0], grid[1], code.sigma_deg)


def _grid_text(layout: CodeLayout) -> str:
    return f"axis-only code, {layout.n_axes} axes" if layout.axis_only else \
        f"full code {layout.n_axes} x {layout.n_angles}"


def _worst(layout: CodeLayout, objects: Mapping[int, Mapping[str, Any]]) -> tuple[int, float] | None:
    """The object whose symmetric peaks merge worst at ``layout`` and its exact-code error [deg], or None."""
    merged = {obj_id: merged_peaks(layout, info) for obj_id, info in objects.items()}
    merged = {obj_id: error for obj_id, error in merged.items() if error is not None}
    return max(merged.items(), key=lambda item: item[1]) if merged else None


def _narrowed(layout: CodeLayout, objects: Mapping[int, Mapping[str, Any]]) -> CodeLayout:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # merged peaks at the narrowest width are what the caller looks at
        return fit_sigma(layout, objects)


def choose_group_code(code: CodeConfig, objects: Mapping[int, Mapping[str, Any]], finer: bool = True) -> GroupCode:
    """The code of the group ``objects`` (see the module docstring); without ``finer`` the size's grid is kept and
    only sigma narrowed."""
    ids = tuple(sorted(objects))
    names = _names(ids)
    size_layout = _layout(code, objects, (code.n_axes, code.n_angles))
    merged_at_size = _worst(size_layout, objects)
    if merged_at_size is None:
        return GroupCode(ids, code, code.sigma_deg,
                         f"{names}: {_grid_text(size_layout)}, sigma {code.sigma_deg:g} deg (the size's settings: "
                         "every symmetric pose stays its own peak)")
    obj_id, error = merged_at_size
    why = (f"at the size's sigma {code.sigma_deg:g} deg object {obj_id}'s {len(symmetry_rotations(objects[obj_id]))} "
           f"symmetric poses merge (an exact code decodes {error:.1f} deg off)")
    grids = finer_grids(code.n_axes, code.n_angles, size_layout.axis_only) if finer else [(code.n_axes, code.n_angles)]
    for grid in grids:
        layout = _narrowed(_layout(code, objects, grid), objects)
        if _worst(layout, objects) is None:
            chosen = replace(code, n_axes=grid[0], n_angles=grid[1], sigma_from_symmetries=True)
            instead = "" if grid == grids[0] else f" instead of the size's {_grid_text(size_layout)}"
            return GroupCode(ids, chosen, layout.sigma_deg,
                             f"{names}: {_grid_text(layout)}{instead}, sigma narrowed to {layout.sigma_deg:g} deg: "
                             f"{why}" + ("" if not instead else "; the size's grid cannot keep them apart at any "
                                                                "sigma it resolves"))
    layout = _narrowed(size_layout, objects)
    worst = _worst(layout, objects) or merged_at_size  # not None: the size's grid was tried above
    tried = f"no grid up to {MAX_NEURONS} neurons keeps them apart" if finer else "the grid is too coarse"
    return GroupCode(ids, replace(code, sigma_from_symmetries=True), layout.sigma_deg,
                     f"{names}: {_grid_text(layout)}, sigma narrowed to {layout.sigma_deg:g} deg: {why}; {tried}, so "
                     f"object {worst[0]} keeps errors of about {worst[1]:.1f} deg even with an exact code")


def _needs(group: GroupCode) -> tuple[int, int, float]:
    return group.code.n_axes, group.code.n_angles, round(group.sigma_deg, 3)


def split_by_code(code: CodeConfig, models_info: Mapping[int, Mapping[str, Any]], group: Sequence[int]
                  ) -> list[GroupCode]:
    """``group`` as models of parts that need the same code alone (grid and width), in order of first id.

    One part with many symmetric poses (a 12-fold gear) would otherwise move every part it is pooled with onto
    its fine grid and narrow width: a head many times larger and targets so narrow that those parts barely train
    in a short budget (bench/results/validation-parts-quick.md). Each split-off model's note says why.
    """
    alone = {obj_id: choose_group_code(code, {obj_id: models_info[obj_id]}) for obj_id in group}
    by_needs: dict[tuple[int, int, float], list[int]] = {}
    for obj_id in sorted(group):
        by_needs.setdefault(_needs(alone[obj_id]), []).append(obj_id)
    chosen = []
    for ids in by_needs.values():
        one = alone[ids[0]] if len(ids) == 1 else choose_group_code(code, {i: models_info[i] for i in ids})
        others = [i for i in sorted(group) if i not in ids]
        if others:
            differ = "code differs" if len(others) == 1 else "codes differ"
            one = replace(one, note=f"{one.note}; a model apart from {_names(others)}, whose {differ}")
        chosen.append(one)
    return chosen


def choose_group_codes(code: CodeConfig, models_info: Mapping[int, Mapping[str, Any]],
                       groups: Sequence[Sequence[int]], finer: bool = True) -> list[GroupCode]:
    """Each group's code, in the groups' order. With ``finer`` a group whose parts need different codes alone is
    split into one model per code (:func:`split_by_code`); without, every group keeps the size's grid."""
    if not finer:
        return [choose_group_code(code, {obj_id: models_info[obj_id] for obj_id in group}, finer) for group in groups]
    return [chosen for group in groups for chosen in split_by_code(code, models_info, group)]
