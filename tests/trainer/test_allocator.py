"""Freed memory kept for the next training step: a step's large blocks reuse the last step's pages."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from popcode_trainer.train import allocator

# A step's shape in miniature: two gradient-sized and two batch-sized blocks, touched, then freed; ten steps.
STEPS = """
import resource, sys
import numpy as np
from popcode_trainer.train.allocator import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else False
def step():
    blocks = [np.ones(size // 8) for size in (12 << 20, 12 << 20, 3 << 20, 3 << 20)]
    del blocks
step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    step()
print(int(kept), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _page_faults(mode: str) -> tuple[bool, int]:
    """(whether the thresholds were set, minor page faults of ten steps) in a fresh process."""
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(STEPS), mode], capture_output=True, text=True,
                            timeout=120, check=True)
    kept, faults = result.stdout.split()
    return kept == "1", int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's thresholds: Linux only")
def test_steps_reuse_freed_pages_once_memory_is_kept() -> None:
    _, plain = _page_faults("plain")
    kept, faults = _page_faults("keep")
    assert kept, "glibc refused the thresholds"
    pages_per_step = (30 << 20) // 4096
    assert plain > 2 * pages_per_step  # the C library's defaults hand the pages back and fault them in again
    assert faults < pages_per_step // 10, f"{faults} page faults in ten steps with freed memory kept"


def test_other_platforms_are_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(allocator.sys, "platform", "darwin")
    monkeypatch.setattr(allocator, "_outcome", [])
    assert allocator.keep_freed_memory() is False and allocator.freed_memory_kept() is False
