"""Fuzz ``PoseEstimator.predict`` with Hypothesis: every call must either return valid rotations or raise
``PopcodeError`` (issue 19). Anything else is unhandled, a call still running after :data:`CALL_LIMIT_S` (its
watchdog) too; Hypothesis then shrinks the call to the smallest one that still fails, and it is saved in
:data:`CASES` (JSON, arrays and non-finite numbers tagged) for the suite to replay (issue 66).

Images of every dtype and shape (NaN, out of range, empty, RGBA) from ``hypothesis.extra.numpy``, boxes from
sub-pixel to 1e300 px, NaN and inf, camera matrices from physical to absurd, ``top_k``/``obj_ids`` of the wrong
type. The suite runs a short fixed-seed fuzz; this script runs a long one on a real model and records it:

    python -m tools.fuzz --calls 5000
"""

from __future__ import annotations

import argparse
import base64
import math
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hypothesis
import numpy as np
from hypothesis import HealthCheck, Phase, Verbosity, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from popcode_runtime import PopcodeError, PoseEstimator
from popcode_runtime.base.files import json_bytes, read_json, write_bytes_atomic
from popcode_trainer.train.deadline import deadline
from tools.command import run_command
from tools.paths import RESULTS, ROOT, SHIPPED_3_6

MAX_SIDE = 400  # images stay small: the fuzz is about arguments, not about pixels
CALL_LIMIT_S = 10.0  # a call still running then is a hang (the slowest calls take about half a second)
CASES = ROOT / "tests" / "fuzz_cases.json"  # the shrunk failing calls, replayed by the suite
IMAGE_DTYPES = (np.uint8, np.uint16, np.float32, np.float64, np.int8, np.int32, np.bool_)
ODD_NUMBERS = (math.nan, math.inf, -math.inf, 1e-9, 1e5, 1e9, 1e300, -1e300)
ODD_VALUES = ("12", None, True, [1.0])


class CallTimeout(BaseException):
    """Raised by the watchdog in a call that ran past its limit (a ``BaseException``: nothing may catch it)."""


class UnhandledCallError(Exception):
    """A call that neither returned valid rotations nor refused in one line: what Hypothesis shrinks."""


def weighted(choices: dict[Any, int]) -> st.SearchStrategy:
    """One of ``choices`` (value -> weight); Hypothesis shrinks towards the first, so the plausible ones lead."""
    return st.sampled_from([value for value, weight in choices.items() for _ in range(weight)])


@st.composite
def images(draw: st.DrawFn) -> Any:
    """Pictures of every dtype and channel count (1-D, empty and non-array ones too), any element values; half of
    them the grey uint8 images a camera gives."""
    side = st.integers(1, MAX_SIDE)
    kind = draw(weighted({"grey": 8, "colour": 2, "any dtype": 3, "channels": 1, "empty": 1, "1-D": 1, "odd": 1}))
    if kind == "odd":
        return draw(st.sampled_from([None, [[0, 1], [2, 3]]]))
    dtype = np.uint8 if kind in ("grey", "channels", "empty") else draw(st.sampled_from(IMAGE_DTYPES))
    shape = {"grey": st.tuples(side, side), "any dtype": st.tuples(side, side),
             "colour": st.tuples(side, side, st.just(3)), "channels": st.tuples(side, side, st.sampled_from([1, 2, 4])),
             "empty": st.tuples(st.integers(0, 1), side), "1-D": st.tuples(side)}[kind]
    return draw(hnp.arrays(dtype, shape))


def numbers(scale: float) -> st.SearchStrategy:
    """A coordinate: mostly in ``[-0.2, 1.2] * scale``, else absurd, non-finite or not a number at all."""
    odd = st.one_of(st.sampled_from(ODD_NUMBERS), st.sampled_from(ODD_VALUES))
    return weighted({"plain": 37, "odd": 3}).flatmap(lambda kind: st.floats(-0.2 * scale, 1.2 * scale)
                                                     if kind == "plain" else odd)


@st.composite
def boxes(draw: st.DrawFn, shape: tuple[int, ...]) -> Any:
    """One box for an image of ``shape``: inside or across its edge, else of odd numbers or not a box."""
    height, width = (shape[0], shape[1]) if len(shape) >= 2 else (MAX_SIDE, MAX_SIDE)
    kind = draw(weighted({"inside": 18, "numbers": 1, "not a box": 1}))
    if kind == "inside":
        w, h = draw(st.floats(2, max(3, width))), draw(st.floats(2, max(3, height)))
        return [draw(st.floats(-w / 2, width)), draw(st.floats(-h / 2, height)), w, h]
    if kind == "numbers":
        return [draw(numbers(width)), draw(numbers(height)), draw(numbers(width)), draw(numbers(height))]
    return draw(st.sampled_from(["0,0,10,10", None, [1.0, 2.0, 3.0], [1, 2, 3, 4, 5]]))


@st.composite
def cameras(draw: st.DrawFn) -> Any:
    """None, a physical ``[fx, fy, cx, cy]``, odd numbers of length 3, 4 or 9, or no camera matrix at all."""
    kind = draw(weighted({"physical": 4, "none": 4, "odd numbers": 1, "not a matrix": 1}))
    if kind == "physical":
        return [draw(st.floats(100, 3000)), draw(st.floats(100, 3000)), draw(st.floats(0, 800)),
                draw(st.floats(0, 600))]
    if kind == "odd numbers":
        length = draw(st.sampled_from([3, 4, 9]))
        return draw(st.lists(numbers(1000.0), min_size=length, max_size=length))
    return None if kind == "none" else draw(st.sampled_from(["500,500,320,240", [[1.0, 2.0], [3.0]], np.eye(2)]))


@st.composite
def predict_calls(draw: st.DrawFn, obj_ids: Sequence[int]) -> dict[str, Any]:
    """Keyword arguments for one ``predict`` call, each argument hostile with some probability."""
    image = draw(images())
    count = draw(weighted({1: 2, 0: 1, 2: 1, 3: 1, 8: 1, 40: 1}))
    found = draw(weighted({"boxes": 32, "odd": 1}).flatmap(
        lambda kind: st.lists(boxes(np.shape(image)), min_size=count, max_size=count) if kind == "boxes"
        else st.sampled_from([None, "boxes", 5])))
    call = {"image": image, "boxes": found, "K": draw(cameras()), "translation": draw(weighted({False: 6, True: 1})),
            "return_code": draw(weighted({False: 4, True: 1})),
            "top_k": draw(weighted({1: 12, 2: 4, 3: 4, 0: 1, -1: 1, "2": 1, 2.5: 1, None: 1, 1000: 1}))}
    ids = draw(weighted({"none": 7, "valid": 2, "odd": 1}))
    if ids == "valid":
        call["obj_ids"] = [draw(st.sampled_from(list(obj_ids)))] * count
    elif ids == "odd":
        call["obj_ids"] = draw(st.sampled_from([[3.7], [99] * count, "7", [None] * count]))
    return call


@dataclass
class FuzzReport:
    """What the calls did: returned rotations, refused with ``PopcodeError``, or anything else (unhandled: another
    exception, invalid rotations, or a hang past the watchdog's limit), each failure as Hypothesis shrank it."""

    calls: int = 0
    returned: int = 0
    refused: int = 0
    unhandled: list[str] = field(default_factory=list)
    shrunk: list[dict[str, Any]] = field(default_factory=list)  # the smallest failing calls, as predict's arguments
    slowest_s: float = 0.0
    refusals: Counter = field(default_factory=Counter)

    def to_dict(self) -> dict[str, Any]:
        return {"calls": self.calls, "returned": self.returned, "refused": self.refused,
                "unhandled": len(self.unhandled), "unhandled_examples": self.unhandled[:10],
                "slowest_call_s": self.slowest_s, "most_common_refusals": self.refusals.most_common(12)}


def _valid(prediction: Any) -> bool:
    R = prediction.R_m2c
    ok = np.isfinite(R).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-5) and abs(np.linalg.det(R) - 1) < 1e-5
    return bool(ok and (prediction.t_m2c_mm is None or np.isfinite(prediction.t_m2c_mm).all()))


def try_call(estimator: Any, arguments: dict[str, Any], report: FuzzReport, limit_s: float = CALL_LIMIT_S) -> None:
    """One ``predict`` call under the watchdog, counted in ``report``; :class:`UnhandledCallError` unless it returned
    valid rotations or refused with ``PopcodeError``."""
    started = time.perf_counter()
    report.calls += 1
    try:
        with deadline(limit_s, CallTimeout(f"still running after {limit_s:g} s")):
            predictions = estimator.predict(**arguments)
    except PopcodeError as error:
        report.refused += 1
        report.refusals[" ".join(str(error).split()[:4])] += 1
        return
    except CallTimeout as error:
        raise UnhandledCallError(f"hang: {error}") from None
    except Exception as error:  # what the fuzz is looking for
        raise UnhandledCallError(f"{type(error).__name__}: {str(error)[:200]}") from error
    finally:
        report.slowest_s = max(report.slowest_s, time.perf_counter() - started)
    if not all(_valid(p) for p in predictions):
        raise UnhandledCallError("returned a rotation that is not one")
    report.returned += 1


def fuzz(estimator: Any, calls: int, seed: int = 0, limit_s: float = CALL_LIMIT_S) -> FuzzReport:
    """``calls`` Hypothesis examples of ``predict``'s arguments from ``seed``, each under a watchdog of ``limit_s``;
    a failure is shrunk to the smallest call that still fails and kept in the report's ``shrunk``."""
    report, failing = FuzzReport(), []
    obj_ids = sorted(estimator.metadata.objects)

    @hypothesis.seed(seed)
    @settings(max_examples=calls, deadline=None, database=None, phases=(Phase.generate, Phase.shrink),
              suppress_health_check=list(HealthCheck), report_multiple_bugs=False, verbosity=Verbosity.quiet)
    @given(predict_calls(obj_ids))
    def one_call(arguments: dict[str, Any]) -> None:
        try:
            try_call(estimator, arguments, report, limit_s)
        except UnhandledCallError:
            failing.append(arguments)  # Hypothesis runs the shrunk call last
            raise

    try:
        one_call()
    except UnhandledCallError as error:
        report.unhandled.append(str(error))
        report.shrunk.append(failing[-1])
    return report


def encode(value: Any) -> Any:
    """``value`` (predict's arguments) as JSON values: arrays and non-finite floats tagged, tuples as lists."""
    if isinstance(value, np.ndarray):
        return {"ndarray": value.dtype.str, "shape": list(value.shape),
                "bytes": base64.b64encode(np.ascontiguousarray(value).tobytes()).decode()}
    if isinstance(value, float) and not math.isfinite(value):
        return {"float": repr(value)}
    if isinstance(value, dict):
        return {"dict": {key: encode(item) for key, item in value.items()}}
    if isinstance(value, list | tuple):
        return [encode(item) for item in value]
    return value


def decode(value: Any) -> Any:
    """The inverse of :func:`encode`."""
    if isinstance(value, list):
        return [decode(item) for item in value]
    if isinstance(value, dict) and "ndarray" in value:
        data = base64.b64decode(value["bytes"])
        return np.frombuffer(data, np.dtype(value["ndarray"])).reshape(value["shape"]).copy()
    if isinstance(value, dict) and "float" in value:
        return float(value["float"])
    if isinstance(value, dict):
        return {key: decode(item) for key, item in value["dict"].items()}
    return value


def read_cases(path: Path = CASES) -> list[dict[str, Any]]:
    """The saved shrunk calls, as ``predict``'s keyword arguments."""
    return [decode(case["call"]) for case in read_json(path)["cases"]] if path.is_file() else []


def save_cases(report: FuzzReport, model: str, path: Path = CASES) -> None:
    """Add the report's shrunk calls to ``path``, each with what it did and on which model."""
    saved = read_json(path)["cases"] if path.is_file() else []
    saved += [{"found": problem, "model": model, "call": encode(call)}
              for problem, call in zip(report.unhandled, report.shrunk, strict=True)]
    write_bytes_atomic(path, json_bytes({"cases": saved}))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", type=Path, default=SHIPPED_3_6)
    parser.add_argument("--calls", type=int, default=5000, help="Hypothesis examples (shrinking calls come on top)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--cases", type=Path, default=CASES, help="where shrunk failing calls are added")
    args = parser.parse_args(argv)
    from tools.report import machine, machine_line, write_results  # torch: the machine record; the fuzz needs none

    cases = args.cases.relative_to(ROOT) if args.cases.is_relative_to(ROOT) else args.cases
    started = time.perf_counter()
    report = fuzz(PoseEstimator(args.model, threads=args.threads), args.calls, args.seed)
    seconds = time.perf_counter() - started
    if report.shrunk:
        save_cases(report, args.model.name, args.cases)
    result = {**report.to_dict(), "model": args.model.name, "seed": args.seed, "seconds": seconds,
              "call_limit_s": CALL_LIMIT_S, "hypothesis": hypothesis.__version__}
    lines = [f"# Fuzz of PoseEstimator.predict ({args.model.name}, Hypothesis {hypothesis.__version__}, seed "
             f"{args.seed})", "",
             "| examples | calls (shrinking included) | returned | refused (PopcodeError) | unhandled | slowest call s "
             "| total s |", "|---:|---:|---:|---:|---:|---:|---:|",
             f"| {args.calls} | {report.calls} | {report.returned} | {report.refused} | {len(report.unhandled)} | "
             f"{report.slowest_s:.2f} | {seconds:.0f} |", "",
             f"Each call ran under a {CALL_LIMIT_S:.0f} s watchdog (one still running then counts as unhandled). "
             f"A failure is shrunk by Hypothesis and added to `{cases}`, which the suite replays.", "",
             "Most common refusals: " + "; ".join(f"{text}... ({n})" for text, n in report.refusals.most_common(8))]
    if report.unhandled:
        lines += ["", "Unhandled (shrunk): " + "; ".join(report.unhandled)]
    lines += ["", machine_line(machine()), "",
              f"Command: `python -m tools.fuzz --calls {args.calls} --seed {args.seed}`"]
    json_path, _ = write_results(args.out, "fuzz", {"fuzz": result}, "\n".join(lines))
    print("\n".join(lines))
    print(f"wrote {json_path}")
    return 1 if report.unhandled else 0


if __name__ == "__main__":
    run_command("tools.fuzz", main)
