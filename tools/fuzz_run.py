"""Fuzz ``popcode run`` with hostile inputs (issue 30): every call must write a results file that holds exactly the
rows its inputs ask for, or refuse in one line (exit 2). Anything else is counted as unhandled.

Each call copies a small rendered split into a fresh folder, applies 1-3 random mutations
(:mod:`tools.run_mutations`) to what ``popcode run`` reads — the detections JSON, the split's JSON files, images and
folder names, the ``<out>.partial`` of an interrupted run, the options — and calls
``popcode_runtime.commands.cli.main`` in-process under a watchdog. A call either starts afresh, resumes the partial
file of a killed run, or interrupts a run itself (``KeyboardInterrupt`` while reading an image: exit 130) and
resumes it, maybe after one more mutation. Unhandled: an exception out of ``main``, a hang, another exit code, more
than one error line, a warning or a library's own line on stderr, a temporary file left, and results that do not
read back, hold rows of images or objects that do not exist or values popcode never writes, are not the rows the
detections ask for, or (for a resumed run) differ from a fresh run's on the same inputs. The suite runs a short
fixed-seed fuzz; this script runs a long one and records it:

    python -m tools.fuzz_run --calls 3000

One call is replayed alone, its folder kept for a look, with ``--call N --keep DIR`` (and the same ``--seed``).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import io
import json
import math
import os
import shutil
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import popcode_runtime.inference.image_loop as image_loop
from popcode_runtime import PoseEstimator
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.bop19_csv import read_bop19_results
from popcode_runtime.bop.detections import ground_truth_boxes
from popcode_runtime.commands.cli import main as popcode
from popcode_trainer.train.deadline import deadline
from tools.command import run_command
from tools.fuzz import CallTimeout
from tools.paths import RESULTS, SHIPPED_MODELS
from tools.run_mutations import MUTATIONS, Call, apply, pick, real, regular, write_inputs

CALL_LIMIT_S = 20.0  # a call still running then is a hang (the slowest calls take about 2 s)
KILL_POINTS = (1, 2, 4)  # images a killed run closed before it died, for the partial files calls resume
MODES = ("detections", "gt")
BASE_OPTIONS: dict[str, str | None] = {"--quiet": None, "--threads": "1"}
NOT_READ = shutil.ignore_patterns("depth", "mask", "mask_visib", ".popcode_records", "models")  # without --depth
HANDLED = ("wrote results", "refused", "refused by argparse", "interrupted")  # anything else is unhandled
# (scenario, weight), and the weights of the mutation groups before a fresh run, before a resume, and between an
# interruption and its resume
SCENARIOS = (("fresh", 5), ("resume", 3), ("interrupt", 2))
BEFORE = {"detections": 4, "split": 4, "options": 2}
RESUMING = {"partial": 5, "detections": 1.5, "split": 1.5, "options": 2}
AFTER_INTERRUPTION = {"partial": 3, "detections": 2, "split": 4, "options": 1}  # inputs changed before the resume


@dataclass(frozen=True)
class Pristine:
    """What every call starts from, made once: the split, its detections, partial files of killed runs (mode,
    images closed -> bytes) and the rows of whole runs (mode -> lines without the time)."""

    split: Path
    models: tuple[str, ...]
    objects: dict[str, frozenset[int]]  # model -> the objects it knows
    detections: list[dict[str, Any]]
    partials: dict[tuple[str, int], bytes]
    whole: dict[str, list[str]]


@dataclass
class Result:
    """What one ``popcode run`` call did."""

    code: int | None  # None: an exception escaped main
    stderr: str
    seconds: float
    escaped: str | None = None  # the exception's traceback
    native: str = ""  # what libraries wrote to file descriptor 2 themselves
    warned: list[str] = field(default_factory=list)
    interrupted: bool = False  # the fuzz's own KeyboardInterrupt was raised
    argparse: bool = False  # argparse ended the call (SystemExit)


@contextlib.contextmanager
def _interrupting(after: int | None) -> Iterator[dict[str, bool]]:
    """Ctrl-C (``KeyboardInterrupt``) while ``popcode run`` reads image ``after + 1``; nothing when None."""
    state, real_read, reads = {"raised": False}, image_loop.read_image, [0]

    def read(*args: Any, **kwargs: Any) -> Any:
        reads[0] += 1
        if after is not None and reads[0] > after:
            state["raised"] = True
            raise KeyboardInterrupt
        return real_read(*args, **kwargs)

    image_loop.read_image = read
    try:
        yield state
    finally:
        image_loop.read_image = real_read


@contextlib.contextmanager
def _native_stderr() -> Iterator[list[str]]:
    """What libraries write to file descriptor 2 themselves (OpenCV's and onnxruntime's logs), which a user sees
    beside popcode's own line: in the list yielded, after the block."""
    text: list[str] = []
    with tempfile.TemporaryFile("w+") as captured:
        saved = os.dup(2)
        os.dup2(captured.fileno(), 2)
        try:
            yield text
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            captured.seek(0)
            text.append(captured.read())


def invoke(argv: Sequence[str], interrupt_after: int | None = None, limit_s: float = CALL_LIMIT_S) -> Result:
    """``popcode`` in-process with its stderr, warnings and run time captured; an exception that escapes is kept."""
    err = io.StringIO()
    started = time.perf_counter()
    with warnings.catch_warnings(record=True) as warned, contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(err), _native_stderr() as native, _interrupting(interrupt_after) as state:
        warnings.simplefilter("always")
        result = Result(None, "", 0.0)
        try:
            with deadline(limit_s, CallTimeout(f"still running after {limit_s:g} s")):
                result.code = popcode(list(argv))
        except SystemExit as exit_:
            result.code, result.argparse = (exit_.code if isinstance(exit_.code, int) else 1), True
        except BaseException:  # what the fuzz is looking for: a hang, a traceback
            result.escaped = traceback.format_exc(limit=-6)
    result.seconds, result.stderr = time.perf_counter() - started, err.getvalue()
    result.native = "".join(native)
    result.warned, result.interrupted = [f"{w.category.__name__}: {w.message}" for w in warned], state["raised"]
    return result


# --- what a successful call must have written ----------------------------------------------------------------------

def _id(name: str) -> int | None:
    return int(name) if name.isascii() and name.isdigit() else None


def split_images(split: Path) -> set[tuple[int, int]]:
    """(scene_id, im_id) of every image file of a split, read by the format alone (not by the runtime)."""
    found = set()
    for scene in split.iterdir() if split.is_dir() else ():
        folder = next((scene / name for name in ("rgb", "gray") if (scene / name).is_dir()), None)
        if _id(scene.name) is None or folder is None:
            continue
        found |= {(_id(scene.name), _id(path.name.rsplit(".", 1)[0])) for path in folder.iterdir()
                  if path.is_file() and not path.name.startswith(".") and _id(path.name.rsplit(".", 1)[0]) is not None}
    return found


def _is_id(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _is_number(value: Any, low: float = -math.inf, high: float = math.inf) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and \
        low <= value <= high


def detection_problem(entry: Any) -> str | None:
    """What makes a detection invalid in the BOP challenge's format, or None (the format's own reading)."""
    if not isinstance(entry, dict):
        return "not an object"
    if not all(_is_id(entry.get(key)) for key in ("scene_id", "image_id", "category_id")):
        return "ids are not whole numbers >= 0"
    box = entry.get("bbox")
    if not isinstance(box, list) or len(box) != 4 or not all(_is_number(v) for v in box) or min(box[2:]) <= 0:
        return f"bbox {box!r:.40}"
    if not _is_number(entry.get("score"), 0.0, 1.0) or not _is_number(entry.get("time", -1.0)):
        return "score outside [0, 1] or time not a number"
    return None


def wanted_rows(call: Call, objects: frozenset[int]) -> Counter | str:
    """(scene_id, im_id, obj_id) of each row a correct run with ``--detections`` writes, or what makes its
    detections file one that must be refused."""
    try:
        entries = json.loads(call.detections_path.read_bytes() if regular(call.detections_path) else b"")
    except (OSError, ValueError) as error:
        return f"the detections file is not JSON ({error})"
    if not isinstance(entries, list):
        return "the detections file is not a list"
    problem = next((f"detection {i}: {p}" for i, e in enumerate(entries) if (p := detection_problem(e))), None)
    if problem is not None:
        return problem
    rows = [(e["scene_id"], e["image_id"], e["category_id"]) for e in entries if e["category_id"] in objects]
    images = sorted({row[:2] for row in rows})[:int(call.options.get("--max-images") or len(rows) + 1)]
    return Counter(row for row in rows if row[:2] in set(images))


def annotated_rows(split: Path) -> Counter:
    """(scene_id, im_id, obj_id) of every instance in the split's ``scene_gt.json`` files that still read as JSON:
    the rows a run with ``--gt-boxes`` may write at most."""
    rows: Counter = Counter()
    for scene in split.iterdir():
        try:
            scene_gt = json.loads((scene / "scene_gt.json").read_bytes() if regular(scene / "scene_gt.json") else b"")
            rows.update((_id(scene.name), _id(key), gt["obj_id"]) for key, gts in scene_gt.items() for gt in gts)
        except (OSError, ValueError, AttributeError, TypeError, KeyError):
            continue
    return rows


def results_problem(call: Call, pristine: Pristine) -> str | None:
    """What is wrong with the results file of a call that exited 0, or None."""
    out = Path(call.out)
    inputs = [real(call.detections_path), *(real(m) for m in call.models)]
    if real(out) in inputs or real(out).is_relative_to(real(call.split)):
        return f"the results were written over an input ({out.name})"
    if call.out.endswith("/"):
        return f"--out {out.name}/ names a folder, yet a file {out.name} was written"
    try:
        estimates = read_bop19_results(out)
    except PopcodeError as error:
        return f"the results do not read back: {error}"
    if out.with_name(out.name + ".partial").exists() or out.with_name(out.name + ".lock").exists():
        return "the .partial or .lock file was left beside the finished results"
    images, objects = split_images(call.split), frozenset().union(*(pristine.objects[m] for m in call.models))
    for e in estimates:
        R = e.R_m2c
        if (e.scene_id, e.im_id) not in images or e.obj_id not in objects:
            return f"a row of scene {e.scene_id} image {e.im_id} object {e.obj_id}, which the split or models lack"
        if not 0.0 <= e.score <= 1.0 or e.time_s < 0:
            return f"a row's score {e.score} is outside [0, 1] or its time {e.time_s} negative"
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0):
            return f"a row's R is no rotation: {R.reshape(-1).tolist()}"
    rows = Counter((e.scene_id, e.im_id, e.obj_id) for e in estimates)
    wanted = wanted_rows(call, objects) if call.mode == "detections" else None
    if isinstance(wanted, str):
        return f"exit 0 although {wanted}"
    if wanted is not None and rows != wanted:
        return f"rows {sorted((rows - wanted).elements())[:3]} more, {sorted((wanted - rows).elements())[:3]} " \
               "fewer than the detections ask for"
    if wanted is None and rows - annotated_rows(call.split):
        return f"rows {sorted((rows - annotated_rows(call.split)).elements())[:3]} of no annotated instance"
    lines = [line.rsplit(",", 1)[0] for line in out.read_text().splitlines()]
    # as sets of lines: a partial file whose closed images were swapped, or had one removed (redone last), gives
    # the same rows in another order, which BOP19 files do not mind
    if not call.changes_rows and sorted(lines) != sorted(pristine.whole[call.mode]):
        return "the rows differ from the uninterrupted run's on the same inputs"
    return None


def judge(call: Call, result: Result, pristine: Pristine) -> tuple[str, str | None]:
    """The call's outcome and, when it is not handled, what went wrong."""
    if result.escaped is not None:
        kind = "hang" if "CallTimeout" in result.escaped.splitlines()[-1] else "exception"
        return kind, result.escaped.strip().splitlines()[-1]
    errors = [line for line in result.stderr.splitlines() if ": error: " in line]
    leftovers = sorted(path.name for path in Path(call.out).parent.glob(".*.tmp"))
    if result.warned:
        return "warning", "; ".join(result.warned)[:300]
    if result.native.strip():
        return "library output on stderr", result.native.strip()[-300:]
    if leftovers:
        return "temporary file left", ", ".join(leftovers)
    if result.code == 130 and result.interrupted and not errors and "popcode: interrupted" in result.stderr:
        return "interrupted", None
    if result.code == 2 and len(errors) == 1:
        prefix = "popcode run: error: " if result.argparse else "popcode: error: "
        if errors[0].startswith(prefix):
            return "refused by argparse" if result.argparse else "refused", None
    if result.code == 2:
        return "not one error line", result.stderr.strip()[-300:]
    if result.code == 0 and not errors:
        problem = results_problem(call, pristine)
        return ("wrong results", problem) if problem else ("wrote results", None)
    return f"exit {result.code}", result.stderr.strip()[-300:]


# --- the calls ----------------------------------------------------------------------------------------------------

def prepare(folder: Path, split: Path, models: Sequence[Path] = SHIPPED_MODELS) -> Pristine:
    """The pristine inputs in ``folder``: a copy of ``split`` (the parts ``popcode run`` reads), detections made from
    its boxes with one more box and one unknown object, partial files of killed runs, rows of whole runs."""
    pristine_split = folder / "split"
    shutil.copytree(split, pristine_split, ignore=NOT_READ)
    rng = np.random.default_rng(30)
    boxes = ground_truth_boxes(pristine_split)
    detections = [{"scene_id": d.scene_id, "image_id": d.im_id, "category_id": d.obj_id, "bbox": list(d.box),
                   "score": round(float(rng.uniform(0.3, 1.0)), 3), "time": 0.01} for d in boxes]
    first = detections[0]
    detections += [{**first, "bbox": [first["bbox"][0] + 2, first["bbox"][1] + 1, *first["bbox"][2:]], "score": 0.4},
                   {**first, "category_id": 42}]
    objects = {str(path): frozenset(PoseEstimator(path).metadata.objects) for path in models}
    base = Call(folder, pristine_split, "", detections, None, b"", [str(path) for path in models],
                dict(BASE_OPTIONS))
    partials, whole = {}, {}
    for mode in MODES:
        for after in (*KILL_POINTS, None):
            call = dataclasses.replace(base, mode=mode, out=str(folder / f"{mode}-{after}.csv"))
            write_inputs(call)
            result = invoke(call.argv(), interrupt_after=after)
            if result.code != (0 if after is None else 130):
                raise RuntimeError(f"the pristine {mode} run (killed after {after}) failed: {result}")
            if after is None:
                whole[mode] = [line.rsplit(",", 1)[0] for line in Path(call.out).read_text().splitlines()]
            else:
                partials[(mode, after)] = Path(call.out + ".partial").read_bytes()
    return Pristine(pristine_split, tuple(base.models), objects, detections, partials, whole)


def _mutate(call: Call, rng: np.random.Generator, weights: dict[str, float], count: int) -> None:
    groups = [group for group in weights if group != "detections" or call.mode == "detections"]
    chances = np.array([weights[group] for group in groups]) / sum(weights[group] for group in groups)
    for _ in range(count):
        apply(pick(rng, MUTATIONS[str(rng.choice(groups, p=chances))]), call, rng)


@dataclass
class Record:
    """One ``popcode run`` call of the fuzz, as the report keeps it."""

    index: int
    step: str  # "run", or "killed"/"resumed" of an interrupted call
    outcome: str
    problem: str | None
    seconds: float
    done: list[str]
    argv: list[str]
    stderr: str
    compared_with_fresh: bool = False  # a resume whose results were compared with a fresh run's


def fuzz_call(pristine: Pristine, seed: int, index: int, workdir: Path, keep: Path | None = None,
              limit_s: float = CALL_LIMIT_S) -> list[Record]:
    """Call ``index`` of the fuzz with ``seed`` (reproducible alone): its one or two ``popcode run`` calls, each
    under a watchdog of ``limit_s``."""
    rng = np.random.default_rng([seed, index])
    folder = keep if keep is not None else Path(tempfile.mkdtemp(prefix=f"call{index}-", dir=workdir))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        mode = "gt" if rng.random() < 0.3 else "detections"
        scenario = pick(rng, [name for name, weight in SCENARIOS for _ in range(weight)])
        after = int(pick(rng, KILL_POINTS))
        shutil.copytree(pristine.split, folder / "split", symlinks=True)
        call = Call(folder, folder / "split", mode, copy.deepcopy(pristine.detections),
                    pristine.partials[(mode, after)] if scenario == "resume" else None,
                    pristine.partials[("gt" if mode == "detections" else "detections", after)], list(pristine.models),
                    dict(BASE_OPTIONS),
                    str(folder / "results.csv"))
        _mutate(call, rng, RESUMING if scenario == "resume" else BEFORE, int(rng.integers(1, 4)))
        write_inputs(call)
        records = []
        if scenario == "interrupt":
            killed = invoke(call.argv(), int(rng.integers(0, 6)), limit_s)
            records.append(_record(index, "killed", call, pristine, killed))
            if rng.random() < 0.5:
                try:
                    partial = Path(call.out + ".partial")
                    call.partial = partial.read_bytes() if regular(partial) else None
                except OSError:  # a name too long
                    call.partial = None
                _mutate(call, rng, AFTER_INTERRUPTION, 1)
                call.done[-1] = "after the interruption, " + call.done[-1]
                write_inputs(call, overwrite=True)
        resuming = _has_partial(call)
        records.append(_record(index, "resumed" if scenario == "interrupt" else "run", call, pristine,
                               invoke(call.argv(), limit_s=limit_s)))
        if resuming and not call.forged and records[-1].outcome == "wrote results":
            records[-1].compared_with_fresh, problem = True, _fresh_run_problem(call, limit_s)
            if problem is not None:
                records[-1].outcome, records[-1].problem = "differs from a fresh run", problem
        return records
    finally:
        if keep is None:
            shutil.rmtree(folder, ignore_errors=True)


def _has_partial(call: Call) -> bool:
    try:
        return Path(call.out + ".partial").is_file()
    except OSError:  # a name too long
        return False


def _fresh_run_problem(call: Call, limit_s: float) -> str | None:
    """What differs between a resumed run's results and those of the same command run afresh on the inputs as they
    are now (times aside, as sets of lines), or None: a resume must never mix in rows of inputs that changed."""
    fresh = dataclasses.replace(call, out=str(call.folder / "fresh" / "results.csv"))
    Path(fresh.out).parent.mkdir(exist_ok=True)
    result = invoke(fresh.argv(), limit_s=limit_s)
    if result.code != 0:
        return f"the resume wrote results, a fresh run refuses: {result.stderr.strip()[-200:]}"
    rows = [sorted(line.rsplit(",", 1)[0] for line in Path(out).read_text().splitlines()) for out in (call.out,
                                                                                                        fresh.out)]
    return None if rows[0] == rows[1] else f"{len(set(rows[0]) ^ set(rows[1]))} lines differ from a fresh run's"


def _record(index: int, step: str, call: Call, pristine: Pristine, result: Result) -> Record:
    outcome, problem = judge(call, result, pristine)
    if result.escaped and problem:
        problem = result.escaped.strip()[-1500:]
    argv = [part.replace(str(call.folder), "<call>") for part in call.argv()]
    return Record(index, step, outcome, problem, result.seconds, list(call.done), argv, result.stderr.strip()[-400:])


def _rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


@dataclass
class RunFuzzReport:
    """The calls' outcomes: handled (results written and right, refused in one line, our own interrupt) or not."""

    cases: int = 0  # each one or two calls of main (an interrupted run and its resume)
    calls: int = 0
    compared_with_fresh: int = 0
    outcomes: Counter = field(default_factory=Counter)
    unhandled: list[Record] = field(default_factory=list)
    refusals: Counter = field(default_factory=Counter)
    mutations: Counter = field(default_factory=Counter)
    slowest: Record | None = None
    rss_mib: list[float] = field(default_factory=list)  # after every tenth of the calls

    def add(self, record: Record) -> None:
        self.calls += 1
        self.outcomes[record.outcome] += 1
        if record.outcome not in HANDLED:
            self.unhandled.append(record)
        if record.outcome.startswith("refused"):
            words = [w for w in record.stderr.splitlines()[-1].split(": error: ", 1)[-1].split() if "/" not in w]
            self.refusals[" ".join(words[:4])] += 1
        if self.slowest is None or record.seconds > self.slowest.seconds:
            self.slowest = record
        self.compared_with_fresh += record.compared_with_fresh

    def to_dict(self) -> dict[str, Any]:
        return {"cases": self.cases, "calls": self.calls, "outcomes": dict(self.outcomes.most_common()),
                "resumes_compared_with_a_fresh_run": self.compared_with_fresh,
                "handled": sum(self.outcomes[o] for o in HANDLED), "unhandled": len(self.unhandled),
                "unhandled_cases": [vars(r) for r in self.unhandled[:20]],
                "slowest_call": vars(self.slowest) if self.slowest else None, "rss_mib": self.rss_mib,
                "mutations": dict(self.mutations.most_common()), "most_common_refusals": self.refusals.most_common(15)}


def fuzz_run(pristine: Pristine, calls: int, seed: int = 0, workdir: Path | None = None,
             limit_s: float = CALL_LIMIT_S) -> RunFuzzReport:
    """``calls`` random cases (each one or two calls of ``popcode run``, each under a watchdog of ``limit_s``) with a
    fixed seed."""
    report = RunFuzzReport()
    with tempfile.TemporaryDirectory(prefix="fuzz-run-", dir=workdir) as scratch:
        for index in range(calls):
            records = fuzz_call(pristine, seed, index, Path(scratch), limit_s=limit_s)
            for record in records:
                report.add(record)
            report.cases += 1
            report.mutations.update(what.split(":")[0].removeprefix("after the interruption, ")
                                    for what in records[-1].done)
            if (index + 1) % max(1, calls // 10) == 0:
                report.rss_mib.append(round(_rss_mib(), 1))
    return report


def markdown(report: RunFuzzReport, seed: int, command: str, seconds: float, machine: str) -> str:
    """The findings as ``bench/results/fuzz-run.md`` holds them."""
    slowest = report.slowest
    assert slowest is not None, "no calls"
    return "\n".join([
        f"# Fuzz of popcode run ({', '.join(p.name for p in SHIPPED_MODELS)}, seed {seed})", "",
        f"Command: `{command}`. A 6-image split rendered with `render_builtin_split(folder, 1, size=(160, 120), "
        "random_position=True)`; each case mutates a copy of it (tools/run_mutations.py) and calls main once, or "
        "twice when it interrupts a run and resumes it.", "", machine, "",
        "| cases | calls of main | " + " | ".join(HANDLED) + " | unhandled | resumes compared with a fresh run "
        "| slowest call s | total s |",
        "|---:|---:|" + "---:|" * (len(HANDLED) + 4),
        f"| {report.cases} | {report.calls} | " + " | ".join(str(report.outcomes[o]) for o in HANDLED) +
        f" | {len(report.unhandled)} | {report.compared_with_fresh} | {slowest.seconds:.2f} | {seconds:.0f} |", "",
        f"Each call ran under a {CALL_LIMIT_S:.0f} s watchdog. Slowest call: case {slowest.index} ({slowest.outcome}; "
        f"{'; '.join(slowest.done)}).", "",
        f"Resident memory (MiB, the process with the renderer loaded) after each tenth of the cases: {report.rss_mib}.",
        "",
        "Unhandled: " + ("none" if not report.unhandled else "; ".join(
            f"case {r.index} {r.step}: {r.outcome} ({(r.problem or '').splitlines()[-1][:120]})"
            for r in report.unhandled[:10])), "",
        "Mutations applied (cases): " + "; ".join(f"{name} {n}" for name, n in report.mutations.most_common()), "",
        "Most common refusals: " + "; ".join(f"{text}... ({n})" for text, n in report.refusals.most_common(10))])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--calls", type=int, default=3000, help="cases to run (each one or two calls of main)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--call", type=int, metavar="N", help="replay case N alone and print what it did")
    parser.add_argument("--keep", type=Path, metavar="DIR", help="with --call: keep the case's folder in DIR")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    from popcode_trainer.data.render import render_builtin_split  # the fuzz calls the runtime; the trainer renders
    from tools.report import machine, machine_line, write_results

    with tempfile.TemporaryDirectory(prefix="fuzz-run-") as work:
        split = render_builtin_split(Path(work) / "rendered", 1, size=(160, 120), random_position=True)
        pristine = prepare(Path(work), split)
        if args.call is not None:
            for record in fuzz_call(pristine, args.seed, args.call, Path(work), keep=args.keep):
                print(json.dumps(vars(record), indent=1))
            return 0
        started = time.perf_counter()
        report = fuzz_run(pristine, args.calls, args.seed, Path(work))
        seconds = time.perf_counter() - started
    command = " ".join(["python -m tools.fuzz_run", *(argv if argv is not None else sys.argv[1:])])
    text = markdown(report, args.seed, command, seconds, machine_line(machine()))
    result = {**report.to_dict(), "seed": args.seed, "seconds": seconds, "command": command,
              "call_limit_s": CALL_LIMIT_S, "models": [path.name for path in SHIPPED_MODELS]}
    json_path, _ = write_results(args.out, "fuzz-run", {"fuzz_run": result}, text)
    print(text)
    print(f"wrote {json_path}")
    return 1 if report.unhandled else 0


if __name__ == "__main__":
    run_command("tools.fuzz_run", main)
