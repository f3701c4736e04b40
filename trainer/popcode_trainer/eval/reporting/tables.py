"""Result tables in the shape of the paper's: per object, and grouped by pose ambiguity.

Scores are fractions in [0, 1]; markdown shows them as percentages, the best
method of each column in bold. JSON keeps the fractions, with ``null`` for a
score that could not be computed (a group without objects, VSD without depth).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

from ...metrics.recall import GROUPS, METRICS, VISIBILITY_BINS
from ..pipeline.translation import SUMMARY_COLUMNS
from .markdown import markdown_table

Scores = Mapping[str, float]  # metric name -> score in [0, 1]


def _percent(value: float | None) -> str:
    return "–" if value is None or math.isnan(value) else f"{100.0 * value:.2f}%"


def _markdown(header: Sequence[str], rows: Sequence[tuple[str, Sequence[float | None]]],
              leading: Sequence[Sequence[Any]] = ()) -> str:
    """A markdown table: first column labels, other columns percentages, the best per column in bold.

    ``leading`` rows are written first, as given (e.g. instance counts).
    """
    columns = list(zip(*(values for _, values in rows), strict=True)) if rows else []
    best = [max((v for v in col if v is not None and not math.isnan(v)), default=None) for col in columns]
    body = [list(row) for row in leading]
    for label, values in rows:
        cells = []
        for value, top in zip(values, best, strict=True):
            text = _percent(value)
            bold = len(rows) > 1 and top is not None and value == top
            cells.append(f"**{text}**" if bold else text)
        body.append([label, *cells])
    return markdown_table(header, body)


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


def visibility_markdown(visibility_by_method: Mapping[str, Mapping[str, Scores]]) -> str:
    """One section per ``visib_fract`` bin (with its instance count), methods as rows, metrics as columns."""
    sections = []
    for label, _, _ in VISIBILITY_BINS:
        section = {method: {k: v for k, v in bins[label].items() if k != "instances"}
                   for method, bins in visibility_by_method.items() if label in bins}
        if not section:
            continue
        count = int(next(iter(visibility_by_method.values()))[label]["instances"])
        sections.append(f"**visib_fract {label}** ({count} instances)\n\n{methods_markdown(section)}")
    return "\n\n".join(sections)


def box_iou_markdown(by_iou_by_method: Mapping[str, Mapping[str, Scores]], metric: str = "MSSD") -> str:
    """One metric per bin of the box's IoU with the truth: bins as columns (with their instance counts), methods
    as rows."""
    labels = list(dict.fromkeys(label for bins in by_iou_by_method.values() for label in bins))
    first = next(iter(by_iou_by_method.values()))
    counts = [["Instances", *(int(first[label]["instances"]) for label in labels)]]
    rows = [(method, [bins[label].get(metric) if label in bins else None for label in labels])
            for method, bins in by_iou_by_method.items()]
    return _markdown([f"{metric} / box IoU", *labels], rows, leading=counts)


def shown_ranks(top_k: int) -> list[int]:
    """The k of the best-of-top-k columns in markdown: every k up to 10, then a few (JSON has all)."""
    if top_k <= 10:
        return list(range(1, top_k + 1))
    return sorted({*range(1, 6), *(k for k in (10, 20, 50) if k < top_k), top_k})


def best_of_top_k_markdown(by_k_by_method: Mapping[str, Mapping[int, Scores | None]], top_k: int) -> str:
    """MSSD of the best of the top-k hypotheses, one section per ambiguity group: methods as rows, k as columns
    (k = 1 is the method's own estimate); "–" where a method lists no hypotheses."""
    ranks = shown_ranks(top_k)
    header = ["Method", *("MSSD (estimate)" if k == 1 else f"MSSD (best of top-{k})" for k in ranks)]
    sections = []
    for group in GROUPS:
        rows = [(method, [None if by_k.get(k) is None else by_k[k].get(group) for k in ranks])
                for method, by_k in by_k_by_method.items()]
        sections.append(f"**{group}**\n\n{_markdown(header, rows)}")
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
    counts = [] if instances_per_object is None else [
        ["Test instances", *(instances_per_object.get(o, 0) for o in obj_ids)]]
    return _markdown([f"{metric} / object", *map(str, obj_ids)], rows, leading=counts)


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(key): _finite_or_none(item) for key, item in value.items()}
    if isinstance(value, float) and math.isnan(value):
        return None
    return value


def to_json(report: Mapping[str, Any]) -> str:
    """JSON text of nested score mappings; NaN becomes ``null`` and keys become strings."""
    return json.dumps(_finite_or_none(report), indent=2, sort_keys=False)


def translation_markdown(rows: Mapping[str, Mapping[str, float]], label: str = "Method") -> str:
    """One row per label (e.g. a method, with its or the ground-truth rotation), the summary as columns."""
    body = [[name, *(f"{100.0 * summary[key]:.1f}%" if key.startswith("within") else f"{summary[key]:.2f}"
                     for key in SUMMARY_COLUMNS)]
            for name, summary in rows.items()]
    return markdown_table([label, *SUMMARY_COLUMNS.values()], body)
