"""Benchmarks, experiments and tools run as a user runs them: ``python -m <module> ...`` from the repository root,
never imported, so that their insides may change without breaking a test."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tools.paths import ROOT

HANG_S = 1800  # a command still running then hangs: the test fails instead of waiting for ever

# ``python -c`` this with FLAGS MODULE ARGS: ``python -m MODULE ARGS`` on a CPU whose feature flags are FLAGS (comma
# separated), as the trainer reads them (``train.fast_path.cpu_flags``), to see what a command chooses on another CPU.
ON_A_CPU_WITH = """import runpy, sys
from popcode_trainer.train import fast_path
flags = frozenset(filter(None, sys.argv[1].split(",")))
fast_path.cpu_flags = lambda: flags
sys.argv = sys.argv[2:]
runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
"""


def run_module(module: str, *args: str | Path, status: int = 0, cpu_flags: frozenset[str] | None = None
               ) -> subprocess.CompletedProcess[str]:
    """``python -m module args`` from the repository root, its output captured; fails unless it exits with
    ``status``. ``cpu_flags``: run it as on a CPU with these flags (``ON_A_CPU_WITH``)."""
    launch = ["-m"] if cpu_flags is None else ["-c", ON_A_CPU_WITH, ",".join(sorted(cpu_flags))]
    done = subprocess.run([sys.executable, *launch, module, *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=HANG_S)
    if done.returncode != status:
        raise AssertionError(f"python -m {module} exited {done.returncode}, not {status}:\n"
                             f"{done.stdout[-2000:]}\n{done.stderr[-4000:]}")
    return done
