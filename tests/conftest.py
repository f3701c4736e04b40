import gc
import os
import sys
from collections import Counter
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs the suite in one pytest-xdist worker per core: each computes on one thread, else the
    # workers' thread pools (torch's OpenMP, MKL, llvmpipe's rasterisers) fight over the cores. Set before torch
    # or Mesa is loaded, and inherited by the processes a test starts; a value set outside wins.
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "LP_NUM_THREADS"):
        os.environ.setdefault(variable, "1")

# A full garbage collection walks every object alive, most of them imported modules: a third of a second each when
# pyrender's renderers still ran one at every close (popcode closes them without it: data/gl.py delete_offscreen).
# What lives after collection, and later what modules a test imported, is frozen out of every later collection
# (gc.freeze); garbage is collected first, so nothing that is garbage then is kept.
REFREEZE_AFTER = 50_000  # new tracked objects at the end of a test module that are worth a collection to freeze


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The modules with a slow test first, the rest by their number of tests: `make test` hands whole modules to
    its workers in this order (--no-loadscope-reorder), so that no module of minutes starts last while the other
    worker has nothing left to do (pytest-xdist's own order, by number of tests, put those few-test modules last).
    A module's tests keep their order and stay together (a stable sort on a key of the module alone)."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    counts = Counter(item.path for item in items)
    items.sort(key=lambda item: (item.path not in slow, -counts[item.path]))


@pytest.hookimpl(trylast=True)
def pytest_collection_finish(session: pytest.Session) -> None:
    gc.collect()
    gc.freeze()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None):
    result = yield
    if nextitem is not None and nextitem.path != item.path and len(gc.get_objects()) > REFREEZE_AFTER:
        gc.collect()
        gc.freeze()
    return result
