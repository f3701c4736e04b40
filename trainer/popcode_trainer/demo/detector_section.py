"""The report's section on the run's own detector: its COCO AP on the cluttered test split, and the bin's pose
scores from its boxes beside the true boxes and detector-like ones, per visible fraction."""

from __future__ import annotations

from collections.abc import Sequence

from ..eval.pipeline.evaluate import MethodResult
from ..eval.reporting.markdown import markdown_table
from .detector_step import OwnDetectorResults

QUICK_DEMO_AP = 0.65  # the goal for the quick demo's detector, AP@[.5:.95]


def _percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f}"


def own_detector_markdown(own: OwnDetectorResults, true_boxes: MethodResult, detector_like: MethodResult | None,
                          link: str, seconds: float | None) -> str:
    """Detection AP / AR, then MSSD from the true, detector-like and the own detector's boxes."""
    scores = own.detection
    coco = scores.coco
    trained = f" trained for {seconds / 60:.1f} min on the training scenes" if seconds else ""
    first_weights = f", first weights from {own.first_weights}" if own.first_weights else ""
    verdict = "met" if (coco.get("AP") or 0.0) >= QUICK_DEMO_AP else "**missed**"
    lines = [
        "## The run's own eyes: a detector from the same renders",
        f"A detector (torchvision FCOS{first_weights}){trained}, run by the runtime alone "
        f"(`popcode detect`, {own.mean_detect_ms:.0f} ms a frame here) on the cluttered test split and scored as the "
        "BOP challenge scores 2-D detection (COCO AP on amodal boxes, instances under 10 % visible ignored). "
        f"Every table of the poses in its boxes (or its detections, where it found none): [{link}]({link}).",
        markdown_table(["AP@[.5:.95]", "AP50", "AP75", "AR@100", "recall ≥ 30 % visible (IoU 0.5)", "goal (AP)"],
                       [[_percent(coco.get("AP")), _percent(coco.get("AP50")), _percent(coco.get("AP75")),
                         _percent(coco.get("AR100")), _percent(scores.recall_goal.recall),
                         f"{100 * QUICK_DEMO_AP:.0f} ({verdict})"]]),
    ]
    rows = [_mssd_row("true boxes", true_boxes, true_boxes)]
    if detector_like is not None:
        rows.append(_mssd_row("detector-like boxes (IoU about 0.75)", detector_like, true_boxes))
    if own.poses is not None:
        rows.append(_mssd_row("the run's own detector (every instance; a missed one is wrong)", own.poses,
                              true_boxes))
    if verdict != "met":
        lines.append("What limits it: its training scenes, then its minutes. On the quick demo's 150 scenes a "
                     "detector's validation loss turns up within minutes; on a validation split four times the "
                     "minutes raised its AP by 3 points, four times the scenes in the same minutes by 16, and the "
                     "shipped detector start (`detector.init`) about doubles it "
                     "(bench/results/eyes.md#the-quick-demos-detector; the shipped detector, trained for 29 minutes on "
                     "3800 scenes at 384 x 288: bench/results/shipped-detector.md). `--size medium` gives it four "
                     "times the time.")
    bins = list(true_boxes.by_visibility)
    lines += ["MSSD of the population code in the bin by where its boxes came from (all objects, then by visible "
              "fraction):",
              markdown_table(["boxes", "MSSD", *(f"visib {label}" for label in bins)], rows)]
    return "\n\n".join(lines)


def _mssd_row(name: str, result: MethodResult, reference: MethodResult) -> Sequence[str]:
    bins = list(reference.by_visibility)
    return [name, _percent(result.groups["All objects"]["MSSD"]),
            *(_percent(result.by_visibility.get(label, {}).get("MSSD")) for label in bins)]
