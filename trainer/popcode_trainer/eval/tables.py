"""Result tables in the shape of the paper's: per object, and grouped by pose ambiguity.

Scores are fractions in [0, 1]; markdown shows them as percentages, the best
method of each column in bold. JSON keeps the fractions, with ``null`` for a
score that could not be computed (a group without objects, VSD without depth).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np

from popcode_runtime.errors import PopcodeError
from popcode_runtime.symmetries import SymmetryClass, symmetry_class

from .scores import METRICS, InstanceErrors, ScoreFunction, Thresholds, metric_scores, scores_per_object

GROUPS = ("Without ambiguity", "With ambiguity", "All objects")

Scores = Mapping[str, float]  # metric name -> score in [0, 1]


def ambiguous_objects(models_info: Mapping[int, Mapping[str, Any]]) -> dict[int, bool]:
    """Object id -> whether its pose is ambiguous (any declared symmetry), from ``models_info.json``."""
    return {int(obj): symmetry_class(info) is not SymmetryClass.NONE for obj, info in models_info.items()}


def group_scores(
    errors: InstanceErrors,
    diameters_mm: Mapping[int, float],
    ambiguous: Mapping[int, bool],
    thresholds: Thresholds | None = None,
    average: Literal["instances", "objects"] = "instances",
    score: ScoreFunction = metric_scores,
) -> dict[str, dict[str, float]]:
    """Scores for the groups of :data:`GROUPS` (the paper's Table IV).

    ``average="instances"`` pools the instances of a group, as the BOP toolkit's
    recall does; ``"objects"`` averages the per-object scores. A group without
    instances has NaN scores. ``score`` computes them (e.g. :func:`.scores.tightest_recalls`).
    """
    obj_ids = np.asarray(errors.obj_id)
    unknown = sorted({int(i) for i in obj_ids} - set(ambiguous))
    if unknown:
        raise PopcodeError(f"no symmetry information for object ids {unknown}")
    is_ambiguous = np.array([ambiguous[int(i)] for i in obj_ids], dtype=bool)
    masks = dict(zip(GROUPS, (~is_ambiguous, is_ambiguous, np.ones_like(is_ambiguous)), strict=True))
    result = {}
    for group, mask in masks.items():
        chosen = errors.select(mask)
        if average == "instances":
            result[group] = score(chosen, diameters_mm, thresholds)
        elif average == "objects":
            per_object = scores_per_object(chosen, diameters_mm, thresholds, score).values()
            names = score(chosen, diameters_mm, thresholds).keys()
            result[group] = {name: float(np.mean([s[name] for s in per_object])) if per_object else math.nan
                             for name in names}
        else:
            raise PopcodeError(f"average must be 'instances' or 'objects', not {average!r}")
    return result


def _percent(value: float | None) -> str:
    return "–" if value is None or math.isnan(value) else f"{100.0 * value:.2f}%"


def _markdown(header: Sequence[str], rows: Sequence[tuple[str, Sequence[float | None]]]) -> str:
    """A markdown table: first column labels, other columns percentages, the best per column in bold."""
    columns = list(zip(*(values for _, values in rows), strict=True)) if rows else []
    best = [max((v for v in col if v is not None and not math.isnan(v)), default=None) for col in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, values in rows:
        cells = []
        for value, top in zip(values, best, strict=True):
            text = _percent(value)
            bold = len(rows) > 1 and top is not None and value == top
            cells.append(f"**{text}**" if bold else text)
        lines.append("| " + " | ".join([label, *cells]) + " |")
    return "\n".join(lines)


def _metrics_present(tables: Sequence[Scores]) -> list[str]:
    present = {name for table in tables for name in table}
    return [name for name in METRICS if name in present]


def methods_markdown(scores_by_method: Mapping[str, Scores]) -> str:
    """Methods as rows, metrics as columns (the paper's Tables V and VI, for one object or group)."""
    metrics = _metrics_present(list(scores_by_method.values()))
    rows = [(method, [scores.get(m) for m in metrics]) for method, scores in scores_by_method.items()]
    return _markdown(["Method", *metrics], rows)


def ambiguity_markdown(groups_by_method: Mapping[str, Mapping[str, Scores]]) -> str:
    """The paper's Table IV: one section per ambiguity group, methods as rows, metrics as columns."""
    sections = []
    for group in GROUPS:
        section = {method: groups[group] for method, groups in groups_by_method.items() if group in groups}
        sections.append(f"**{group}**\n\n{methods_markdown(section)}")
    return "\n\n".join(sections)


def per_object_markdown(
    per_object_by_method: Mapping[str, Mapping[int, Scores]],
    metric: str = "MSSD",
    instances_per_object: Mapping[int, int] | None = None,
) -> str:
    """The paper's Table III: objects as columns, one metric, methods as rows (and test instance counts)."""
    obj_ids = sorted({obj for per_object in per_object_by_method.values() for obj in per_object})
    rows = [
        (method, [per_object.get(obj, {}).get(metric) for obj in obj_ids])
        for method, per_object in per_object_by_method.items()
    ]
    table = _markdown([f"{metric} / object", *map(str, obj_ids)], rows)
    if instances_per_object is None:
        return table
    counts = "| Test instances | " + " | ".join(str(instances_per_object.get(o, 0)) for o in obj_ids) + " |"
    header, rule, *body = table.split("\n")
    return "\n".join([header, rule, counts, *body])


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(key): _finite_or_none(item) for key, item in value.items()}
    if isinstance(value, float) and math.isnan(value):
        return None
    return value


def to_json(report: Mapping[str, Any]) -> str:
    """JSON text of nested score mappings; NaN becomes ``null`` and keys become strings."""
    return json.dumps(_finite_or_none(report), indent=2, sort_keys=False)
