"""How far to trust each estimate: the confidence table and the reliability diagram of an evaluation.

A calibrated confidence is judged on both counts (ECE and the reliability
diagram for calibration; AUROC and the MSSD of the most confident estimates for
usefulness); a method without a calibrator is judged on its raw score, for
usefulness only, since a raw score is not a probability.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from matplotlib.figure import Figure

from ...metrics.confidence import COVERAGES
from ..pipeline.evaluate import MethodResult
from .figures import save_figure
from .markdown import markdown_table

RELIABILITY_PNG = "reliability.png"


def _percent(value: float | None) -> str:
    return "–" if value is None or math.isnan(value) else f"{100.0 * value:.1f}%"


def confidence_markdown(results: Sequence[MethodResult]) -> str:
    """One row per method: what its score is, how often it is right, calibration and usefulness."""
    judged = [r for r in results if r.confidence is not None]
    if not judged:
        return ""
    header = ["Method", "score", "right (error < threshold)", "ECE", "AUROC",
              *(f"MSSD, most confident {100 * c:g} %" for c in COVERAGES)]
    rows = []
    for result in judged:
        c = result.confidence
        rows.append([result.name, f"{c.kind}, {c.threshold_deg:g} deg", _percent(c.accuracy),
                     "–" if c.ece is None else f"{c.ece:.3f}", "–" if math.isnan(c.auroc) else f"{c.auroc:.3f}",
                     *(_percent(c.mssd_at_coverage[coverage]) for coverage in COVERAGES)])
    note = ("An estimate is right when its rotation error up to the object's symmetries is below the threshold. "
            "ECE: the mean gap between confidence and the share right, over 10 confidence bins (0 is perfectly "
            "calibrated; only for a calibrated probability). AUROC: the chance that a right estimate scores above "
            "a wrong one (0.5 is chance). MSSD of the estimates a robot keeps when it acts only on the most "
            "confident share.")
    return "\n\n".join(["## Confidence", note, markdown_table(header, rows)])


def plot_reliability(results: Sequence[MethodResult], path: str | Path) -> Path | None:
    """Share right against mean confidence per bin for every calibrated method; None when there is none."""
    calibrated = [r for r in results if r.confidence is not None and r.confidence.ece is not None]
    if not calibrated:
        return None
    figure = Figure(figsize=(4.6, 4.2), dpi=150)
    axes = figure.add_subplot()
    axes.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="perfectly calibrated")
    for result in calibrated:
        bins = result.confidence.reliability
        axes.plot([b["confidence"] for b in bins], [b["accuracy"] for b in bins], marker="o",
                  label=f"{result.name} (ECE {result.confidence.ece:.3f})")
    threshold = calibrated[0].confidence.threshold_deg
    axes.set(xlim=(0, 1), ylim=(0, 1), xlabel="confidence (mean of the bin)",
             ylabel=f"share with rotation error < {threshold:g} deg", title="Reliability")
    axes.legend(loc="upper left", fontsize=7)
    return save_figure(figure, path)
