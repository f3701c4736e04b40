"""Shared output of the benchmarks, experiments and fuzzers: a JSON file that names the machine beside the markdown
findings."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from popcode_runtime.base.files import write_bytes_atomic
from popcode_trainer.eval.reporting.machine import machine

__all__ = ["machine", "machine_line", "write_results"]


def machine_line(description: dict[str, Any]) -> str:
    """One markdown line naming the machine, its load and the library versions of a :func:`machine` record."""
    flags = ", ".join(description.get("cpu_flags", [])) or "no flags read"
    return (f"Machine: {description['cpu']} ({flags}), {description['cores']} cores, load "
            f"{description['load_average_1m']:.2f}; Python {description['python']}, torch {description['torch']}, "
            f"numpy {description['numpy']}, onnxruntime {description['onnxruntime']}.")


def write_results(out_dir: str | Path, name: str, payload: dict[str, Any], markdown: str) -> tuple[Path, Path]:
    """Write ``<name>.json`` (payload + machine) and ``<name>.md`` into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, md_path = out_dir / f"{name}.json", out_dir / f"{name}.md"
    write_bytes_atomic(json_path, (json.dumps({"machine": machine(), **payload}, indent=1) + "\n").encode())
    write_bytes_atomic(md_path, (markdown + "\n").encode())
    return json_path, md_path
