"""Which first weights each model of a demo took (random, or a pretrained start: train.pretrained), for the report."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from popcode_runtime.base.files import read_json

from ..train.run_files import START_FILE


def first_weights(run_dirs: Iterable[Path]) -> dict[str, str]:
    """Per model folder, the line its training wrote about its first weights ("unknown": a run of an older trainer)."""
    found = {}
    for folder in run_dirs:
        path = folder / START_FILE
        found[folder.name] = str(read_json(path)["start"]) if path.is_file() else "unknown (an older trainer)"
    return found


def first_weights_text(run_dirs: Iterable[Path]) -> str:
    """The report's sentence: one start for every model, or each model's."""
    starts = first_weights(run_dirs)
    if len(set(starts.values())) == 1:
        return f"Every model started from {next(iter(starts.values()))}."
    return "First weights: " + "; ".join(f"`{name}` from {line}" for name, line in starts.items()) + "."
