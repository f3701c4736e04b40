"""The report's section on path-traced test images: the population code's scores on the same images as the
rasteriser and as a physically based path tracer drew them, so a user sees what to expect on a real camera."""

from __future__ import annotations

from typing import Any

from ..eval.reporting.markdown import markdown_table
from .path_traced_step import PathTracedResults

GAP_RESULTS = "bench/results/path-traced.md"  # the shipped models' gap on larger validation splits


def path_traced_markdown(results: PathTracedResults, link: str) -> str:
    """MSSD, MSPD and ADI of both looks and their difference, all objects and per object."""
    title = "## What to expect on a real camera: path-traced test images"
    if results.rendered is None or results.path_traced is None:
        return f"{title}\n\nSkipped: {results.skipped}"
    rendered, traced = results.rendered, results.path_traced
    metrics = ("MSSD", "MSPD", "ADI")
    rows = [[look, *(f"{100 * result.groups['All objects'][m]:.1f}" for m in metrics)]
            for look, result in (("rendered (as trained)", rendered), ("path traced", traced))]
    rows.append(["difference", *(f"{100 * (traced.groups['All objects'][m] - rendered.groups['All objects'][m]):+.1f}"
                                 for m in metrics)])
    interval = ""
    if results.mssd is not None:
        low, high = results.mssd.interval
        interval = (f" The MSSD difference, instance by instance, lies within [{100 * low:+.1f}, {100 * high:+.1f}] "
                    f"with 95 % confidence (bootstrap over the {results.mssd.instances} instances): a difference "
                    "inside it is noise of the few images drawn.")
    per_object = ", ".join(f"{obj_id}: {100 * rendered.per_object[obj_id]['MSSD']:.0f} → "
                           f"{100 * traced.per_object[obj_id]['MSSD']:.0f}" for obj_id in sorted(rendered.per_object))
    return "\n\n".join([
        title,
        f"The first {results.images} images of the clean test split drawn again by a physically based path tracer "
        "(Mitsuba 3 through `popcode-train path-trace`: rough aluminium, steel, grey and black plastic, area lights, "
        "interreflections, render noise) and scored with the same population-code models, ground-truth boxes. The "
        "models never saw such an image: the difference is what the renderer's look costs them, a first idea of "
        f"what a real camera costs. Tables: [{link}]({link}). The shipped models on larger validation splits, and "
        f"what closes the gap: {GAP_RESULTS}.",
        markdown_table(["images", *metrics], rows),
        f"MSSD per object, rendered → path traced: {per_object}.{interval}",
    ])


def path_traced_summary(results: PathTracedResults | None) -> dict[str, Any]:
    if results is None:
        return {}
    if results.rendered is None or results.path_traced is None:
        return {"skipped": results.skipped}
    return {"images": results.images, "rendered": results.rendered.groups, "path_traced": results.path_traced.groups,
            "mssd_difference": results.mssd.to_dict() if results.mssd else None}
