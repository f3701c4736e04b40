"""Epochs fitted to a wall-clock budget, so a run uses the minutes it is given on whatever machine it meets.

At the demo's budget every model is far from converged (bench/results/budget-quick-hybrid.md), so each
minute of training a machine can spare is accuracy, and a slower machine must not overrun. Every model
of the run first trains one epoch; the seconds those epochs took give the cost of one more epoch of all
models together, and the run trains as many epochs as fit in what the budget leaves. Every model then
resumes to that many epochs, so the representations stay on equal terms (same epochs, data and network).
A compiled step's compile (``compile_seconds`` of the metrics) is a one-time cost and is left out of an
epoch's cost (a compile of the quick network took 72 s on 2 threads of an AMX CPU, eight times its epoch:
counted per epoch it would have cost most of them). The resume, in the same process, finds torch's compile
caches warm (its compile took 0.07 s after a first one of 17 s on an AVX2 CPU), so nothing is reserved for it.
The resume keeps the first epoch's choice to compile or not (:func:`~popcode_trainer.demo.steps.train_and_export`).
The fit is written to the run folder, so an interrupted run resumes with the same epochs.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json, write_json_atomic

from ..train.run_files import read_metrics

FIT_FILE = "epochs.json"


@dataclass(frozen=True)
class EpochFit:
    """The epochs chosen for a budget and what they were chosen from."""

    epochs: int
    budget_s: float  # the whole run's wall-clock budget
    seconds_left: float  # what the budget left for training after the first epochs and the other steps
    first_epoch_seconds: dict[str, float]  # per model (run folder name): its first epoch
    bounds: tuple[int, int]


def first_epoch_seconds(run_dir: Path) -> float:
    """Seconds of the training loop of a run's first epoch without its compile, from its metrics (for a run that
    trained it before): what each further epoch costs."""
    return _first_epoch(run_dir, "seconds") - first_epoch_compile_seconds(run_dir)


def first_epoch_compile_seconds(run_dir: Path) -> float:
    """Seconds the first epoch spent compiling the step (0 for an eager step, or metrics of an older trainer): a
    one-time cost (a resume in the same process finds torch's compile caches warm)."""
    try:
        return _first_epoch(run_dir, "compile_seconds")
    except PopcodeError:
        return 0.0


def _first_epoch(run_dir: Path, column: str) -> float:
    try:
        return float(read_metrics(run_dir, (column,))[column][0])
    except PopcodeError as error:
        raise PopcodeError(f"no first epoch to time: {error}") from error


def fitted_epochs(epoch_seconds: float, seconds_left: float, bounds: tuple[int, int]) -> int:
    """The first epoch plus as many more of ``epoch_seconds`` as fit in ``seconds_left``, within ``bounds``."""
    lowest, highest = bounds
    if not 1 <= lowest <= highest:
        raise PopcodeError(f"epoch bounds {bounds} must satisfy 1 <= lowest <= highest")
    if not epoch_seconds > 0:
        raise PopcodeError(f"an epoch must take some time, not {epoch_seconds} s")
    more = math.floor(max(seconds_left, 0.0) / epoch_seconds)
    return int(min(max(1 + more, lowest), highest))


def fit(first_epochs: dict[str, float], budget_s: float, seconds_left: float, bounds: tuple[int, int]) -> EpochFit:
    """The :class:`EpochFit` for models whose first epochs took ``first_epochs`` seconds."""
    epochs = fitted_epochs(sum(first_epochs.values()), seconds_left, bounds)
    return EpochFit(epochs, budget_s, seconds_left, dict(first_epochs), bounds)


def save(result: EpochFit, out_dir: Path) -> Path:
    path = out_dir / FIT_FILE
    write_json_atomic(path, asdict(result))
    return path


def load(out_dir: Path) -> EpochFit | None:
    """The fit an earlier (interrupted) run of this folder made, or None."""
    path = out_dir / FIT_FILE
    if not path.exists():
        return None
    data = read_json(path)
    try:
        return EpochFit(int(data["epochs"]), float(data["budget_s"]), float(data["seconds_left"]),
                        {str(k): float(v) for k, v in data["first_epoch_seconds"].items()},
                        (int(data["bounds"][0]), int(data["bounds"][1])))
    except (KeyError, TypeError, ValueError, IndexError) as error:
        raise PopcodeError(f"{path}: not an epoch fit ({error}); delete it to fit again") from error
