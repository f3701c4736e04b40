"""``popcode-train kit``: check a models folder and a budget, run the demo's pipeline at the size the budget buys
(:mod:`popcode_trainer.kit.budget`) into ``KIT/work``, and lay its models, detector and samples out in ``KIT`` with
a card (:mod:`popcode_trainer.kit.layout`).

``KIT/kit.json`` records what the kit was started with (the models folder, a fingerprint of its files, the
budget) before the long work, so rerunning the same command resumes it (every step of the demo resumes; a demo that
finished, its ``summary.json`` written, is not run again: the kit is laid out from that summary), and a
changed command or models folder is refused in one line that names the change. A folder that holds files but
no ``kit.json`` is another program's and is refused too. One kit command writes a folder at a time.
"""

from __future__ import annotations

import shlex
from dataclasses import replace
from pathlib import Path
from typing import Any

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json, refuse_inputs, write_json_atomic
from popcode_runtime.base.output_lock import OutputLock
from popcode_runtime.commands.run_fingerprint import file_digest

from ..data.path_trace import INSTALL_HINT
from ..demo.files import REPORT_FILE, SUMMARY_FILE
from ..demo.parts import MODELS_INFO, Parts
from ..demo.plan import minutes_text, plan
from ..demo.report import POPCODE
from ..demo.run import prepare_parts, run_demo
from ..demo.sizes import HIDDEN_SIZES, SMOKE_LATENCY_ITERATIONS, DemoSize
from ..demo.steps import PipelineSize
from ..eval.reporting.machine import machine
from .budget import DETECTOR_SHARE, check_hours, kit_size
from .layout import write_kit

KIT_FILE = "kit.json"
KIT_LOCK = "kit.lock"
WORK_FOLDER = "work"
BUDGET = "budget"  # the size a kit takes from its --hours (the hidden sizes are for tests)
LATENCY_ITERATIONS = 50
LOWEST_EPOCHS = DemoSize.epoch_bounds[0]  # the fewest epochs a budget's fit trains (the demo's default bounds)


def run_kit(objects: str | Path, out: str | Path, hours: float, size_name: str = BUDGET) -> dict[str, Any]:
    """Make (or resume) the kit of ``objects`` in ``out`` with a budget of ``hours``; returns ``kit.json``'s record.

    ``size_name``: :data:`BUDGET`, or a hidden demo size whose fixed epochs replace the budget (tests)."""
    out, hours = Path(out), check_hours(hours)
    if size_name != BUDGET and size_name not in HIDDEN_SIZES:
        raise PopcodeError(f"unknown kit size {size_name!r}")
    refuse_inputs(out, "--out", [objects])
    _refuse_foreign(out)
    size = kit_size(hours) if size_name == BUDGET else replace(HIDDEN_SIZES[size_name].pipeline,
                                                                 representations=(POPCODE,))
    print(f"checking the parts of {objects}", flush=True)
    parts, codes = prepare_parts(objects, size.config.code)
    least_s = plan(size.with_epochs(LOWEST_EPOCHS), [list(g.obj_ids) for g in codes], len(parts.obj_ids),
                   fit_epochs=True).remaining_s()
    started = {"objects": str(Path(objects).resolve()), "hours": hours, "size": size_name,
               "files": fingerprint(parts)}
    command = " ".join(["popcode-train kit", "--objects", shlex.quote(str(objects)), "--out", shlex.quote(str(out)),
                        "--hours", f"{hours:g}", *(["--size", size_name] if size_name != BUDGET else [])])
    out.mkdir(parents=True, exist_ok=True)
    with OutputLock(out / KIT_LOCK, f"another popcode-train kit is writing {out} (it holds {KIT_LOCK}); wait for it "
                                    "to end, or give another --out"):
        record = _resume_or_start(out, started)
        if "kit" in record:
            print(f"{out} is complete: {record['kit']['card']}", flush=True)
            return record
        print(plan_text(size, hours, size_name), flush=True)
        if size_name == BUDGET and least_s > 3600.0 * hours:
            print(f"note: with {len(parts.obj_ids)} parts the steps and the lowest {LOWEST_EPOCHS} epochs take about "
                  f"{minutes_text(least_s)} on a 2-core CPU, more than --hours {hours:g}: the kit will take longer "
                  "on a machine like that", flush=True)
        minutes = 60.0 * hours if size_name == BUDGET else None
        iterations = LATENCY_ITERATIONS if size_name == BUDGET else SMOKE_LATENCY_ITERATIONS
        summary = finished_demo(out / WORK_FOLDER) or run_demo(
            f"kit {hours:g} h", out / WORK_FOLDER, size, latency_iterations=iterations, minutes=minutes,
            objects=objects)
        record = {**record, "kit": write_kit(summary, out, command, machine())}
        write_json_atomic(out / KIT_FILE, record)
        print(f"kit written to {out}: card {record['kit']['card']}", flush=True)
        return record


def plan_text(size: PipelineSize, hours: float, size_name: str) -> str:
    """What the budget buys, said before the long work (the demo's plan then gives each step's estimate)."""
    if size_name != BUDGET:
        return f"kit at the hidden size {size_name} (its scores mean nothing)"
    traced = (f", {size.traced_train_images} path-traced images a part" if size.traced_train_images
              else ", no path-traced training images")
    if not size.traced_train_images and kit_size(hours, path_tracing=True).traced_train_images:
        traced += f" (the budget buys them, but the path tracer is not installed: {INSTALL_HINT})"
    return (f"kit for {hours:g} h ({minutes_text(3600.0 * hours)}): {size.train_images_per_object} images a part, "
            f"{size.train_scenes} bin scenes{traced}; trunk {list(size.config.network.conv_channels)}; the detector "
            f"{minutes_text(size.detector_seconds)} ({100 * DETECTOR_SHARE:g} %); the pose models' epochs fitted to "
            "what is left on this machine (what budgets of 0.2 to 1 h buy: docs/training.md#kit)")


def finished_demo(work: Path) -> dict[str, Any] | None:
    """The summary of the demo that finished in ``work`` (the demo writes it last, atomically), so that a kit cut off
    after its demo resumes in seconds instead of evaluating, timing and drawing again; None where the demo has not
    finished there, where the summary names another folder (a moved kit: the demo runs again, its training
    resumes), where a file the kit copies is gone or where the summary lacks what the kit reads (another
    version's)."""
    path = work / SUMMARY_FILE
    if not path.is_file():
        return None
    summary = read_json(path)
    try:
        here = Path(summary["report"]).resolve() == (work / REPORT_FILE).resolve()
        copied = [*summary["models"][POPCODE], *summary["quantised_models"], summary["samples"]]
        present = all(Path(p).is_file() for p in copied)
    except (KeyError, TypeError):
        return None
    return summary if here and present else None


def fingerprint(parts: Parts) -> dict[str, str]:
    """SHA-256 of the models folder's files the kit reads (``models_info.json`` and each listed mesh); none for the
    built-in parts."""
    if parts.source is None:
        return {}
    names = [MODELS_INFO, *(f"obj_{obj_id:06d}.ply" for obj_id in parts.obj_ids)]
    return {name: file_digest(parts.source / name) for name in names}


def _text(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _refuse_foreign(out: Path) -> None:
    """A folder with files but no ``kit.json`` holds someone else's work: never write into it."""
    if out.exists() and not out.is_dir():
        raise PopcodeError(f"--out {out} is a file, not a folder: give a new or empty folder for the kit")
    if out.is_dir() and not (out / KIT_FILE).is_file() and any(p.name != KIT_LOCK for p in out.iterdir()):
        raise PopcodeError(f"--out {out} holds files that are not a popcode kit's (no {KIT_FILE}): give a new or "
                           "empty folder")


def _resume_or_start(out: Path, started: dict[str, Any]) -> dict[str, Any]:
    """The record of a kit started with the same command and files, or a new one; anything else is refused."""
    path = out / KIT_FILE
    if not path.is_file():
        write_json_atomic(path, started)
        return started
    earlier = read_json(path)
    if not isinstance(earlier, dict) or not {"objects", "hours", "size", "files"} <= set(earlier):
        raise PopcodeError(f"{path} is not a kit record: delete {out} to start over, or give another --out")
    for key, option in (("objects", "--objects"), ("hours", "--hours"), ("size", "--size")):
        if earlier[key] != started[key]:
            raise PopcodeError(f"{out} holds a kit started with {option} {_text(earlier[key])}, not "
                               f"{_text(started[key])}: rerun "
                               "that command to resume it, or give another --out")
    changed = sorted(set(earlier["files"]) ^ set(started["files"])
                     | {n for n in set(earlier["files"]) & set(started["files"])
                        if earlier["files"][n] != started["files"][n]})
    if changed:
        raise PopcodeError(f"the models folder {started['objects']} changed since {out} was started "
                           f"({', '.join(changed)}): a kit is trained on one set of parts; give another --out for "
                           "the new ones")
    return earlier
