"""The report's section on parts that look symmetric but for a small feature: how often the population code found
the right pose rather than a look-alike one (:mod:`popcode_trainer.metrics.look_alike_share`)."""

from __future__ import annotations

import numpy as np

from ..eval.pipeline.evaluate import MethodResult
from ..eval.reporting.markdown import markdown_table
from ..metrics.look_alike_share import FOUND_DEG, LookAlikeShare, look_alike_shares


def shares_of(result: MethodResult) -> list[LookAlikeShare]:
    """The look-alike shares of one method's estimates on its split (none when no part of it is a look-alike)."""
    if not result.look_alikes:
        return []
    R_true = np.stack([instance.R_m2c for instance in result.split.instances])
    return look_alike_shares(result.R_est, R_true, result.errors.obj_id, result.split.models_info, result.look_alikes)


def look_alike_markdown(clean: MethodResult, cluttered: MethodResult | None = None) -> str:
    """One row per look-alike part: its look-alike poses and the right pose's share on each split ("" when none)."""
    splits = [("clean split", shares_of(clean))] + ([("cluttered split", shares_of(cluttered))] if cluttered else [])
    by_part: dict[int, dict[str, LookAlikeShare]] = {}
    for name, shares in splits:
        for share in shares:
            by_part.setdefault(share.obj_id, {})[name] = share
    if not by_part:
        return ""
    header = ["object", "look-alike poses", *(f"right pose, {name}" for name, _ in splits)]
    rows = [[str(obj_id), str(next(iter(found.values())).poses),
             *(_cell(found.get(name)) for name, _ in splits)] for obj_id, found in sorted(by_part.items())]
    return ("## Parts that look symmetric\n\n"
            f"These parts nearly have a symmetry they do not declare. Of the {clean.name} estimates within "
            f"{FOUND_DEG:g} deg of the truth up to the look-alike poses (the shape found), the share within "
            f"{FOUND_DEG:g} deg of the truth itself (the feature that breaks the symmetry seen); a network blind to "
            "the feature scores about one over the look-alike poses.\n\n" + markdown_table(header, rows))


def _cell(share: LookAlikeShare | None) -> str:
    if share is None or share.found_shape == 0:
        return "–"
    return f"{100 * share.right_share:.0f} % of {share.found_shape}"
