"""The layering of docs/architecture.md, held by a test so that it cannot drift.

Every import statement of the two packages is read (function-level ones too,
since a lazy import is still an arrow) and checked against the rooms' order:
the runtime needs nothing of the trainer and nothing beyond numpy, onnxruntime
and OpenCV; inside each package every room imports only the rooms below it, the
trainer's metrics are a pure numpy leaf, and no module reaches itself through
its imports.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ROOT / "runtime" / "popcode_runtime"
TRAINER = ROOT / "trainer" / "popcode_trainer"

# Lowest first: a room may import itself and the rooms before it (the trainer's also the runtime), nothing after it.
RUNTIME_ROOMS = ("base", "geometry", "coding", "depth", "bop", "model", "inference", "ros", "commands")
TRAINER_ROOMS = ("metrics", "data", "train", "export", "detection", "eval", "demo", "kit", "commands")
# Inside eval the same rule: the pipeline computes results, reporting only writes them.
EVAL_PARTS = ("pipeline", "reporting")
# Packages each part may import besides the standard library and its own package.
RUNTIME_THIRD_PARTY = {"numpy", "onnxruntime", "cv2"}
# scipy: the KD-tree of the BOP toolkit's ADI; pycocotools: 2-D detection AP, as the BOP toolkit scores it
METRICS_THIRD_PARTY = {"numpy", "scipy", "pycocotools", "popcode_runtime"}


def module_name(path: Path, package_dir: Path) -> str:
    parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path, package_dir: Path) -> set[str]:
    """Absolute names of every module ``path`` imports (``from x import y`` counts as x and x.y)."""
    name = module_name(path, package_dir)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            found.add(source)
            found.update(f"{source}.{alias.name}" for alias in node.names)
    return found


def modules_of(package_dir: Path) -> dict[str, set[str]]:
    return {module_name(path, package_dir): imported_modules(path, package_dir)
            for path in sorted(package_dir.rglob("*.py"))}


def top_level(name: str) -> str:
    return name.split(".")[0]


def is_third_party(name: str) -> bool:
    return top_level(name) not in sys.stdlib_module_names and not name.startswith("__future__")


RUNTIME_IMPORTS = modules_of(RUNTIME)
TRAINER_IMPORTS = modules_of(TRAINER)
TRAINER_MODULES = set(TRAINER_IMPORTS)


RUNTIME_MODULES = set(RUNTIME_IMPORTS)


def room_of(module: str) -> str:
    """``<package>.<room>...``: the room, or '' for a package's own top-level modules (cli, __init__)."""
    parts = module.split(".")
    rooms = RUNTIME_ROOMS if parts[0] == "popcode_runtime" else TRAINER_ROOMS
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in rooms) else ""


def arrows(imports: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported module of the same package) for every import inside one package."""
    modules = set(imports)
    return [(source, target) for source, targets in imports.items() for target in sorted(targets)
            if target in modules]


def trainer_arrows() -> list[tuple[str, str]]:
    return arrows(TRAINER_IMPORTS)


def against_the_order(imports: dict[str, set[str]], rooms: tuple[str, ...]) -> list[str]:
    """The arrows from a room to a room above it."""
    return [f"{source} -> {target}" for source, target in arrows(imports)
            if room_of(source) and room_of(target) and rooms.index(room_of(target)) > rooms.index(room_of(source))]


def test_the_layering_reads_every_module():
    # A parser that found nothing would let every rule below pass.
    assert {"popcode_runtime.inference.estimator", "popcode_trainer.train.loop",
            "popcode_trainer.metrics.pose_errors"} <= RUNTIME_MODULES | TRAINER_MODULES
    assert ("popcode_trainer.demo.run", "popcode_trainer.eval.pipeline.evaluate") in trainer_arrows()
    assert {room_of(module) for module in TRAINER_MODULES} == {*TRAINER_ROOMS, ""}
    assert ("popcode_runtime.inference.estimator", "popcode_runtime.model.engine") in arrows(RUNTIME_IMPORTS)
    assert {room_of(module) for module in RUNTIME_MODULES} == {*RUNTIME_ROOMS, ""}


def test_against_the_order_finds_an_upward_arrow():
    upward = {"popcode_runtime.base.files": {"popcode_runtime.model.engine"}, "popcode_runtime.model.engine": set()}
    assert against_the_order(upward, RUNTIME_ROOMS) == ["popcode_runtime.base.files -> popcode_runtime.model.engine"]


def test_every_runtime_module_is_in_a_room():
    # the package's own top level holds only what a user imports from it: the public API
    loose = sorted(module for module in RUNTIME_MODULES if not room_of(module) and module != "popcode_runtime")
    assert not loose, f"runtime modules outside the rooms {RUNTIME_ROOMS}: {loose}"


def test_runtime_rooms_import_only_the_rooms_below_them():
    wrong = against_the_order(RUNTIME_IMPORTS, RUNTIME_ROOMS)
    assert not wrong, "arrows against docs/architecture.md's layering of the runtime:\n" + "\n".join(wrong)


@pytest.mark.parametrize("module", sorted(RUNTIME_IMPORTS))
def test_runtime_needs_only_numpy_onnxruntime_and_opencv(module):
    outside = sorted(name for name in RUNTIME_IMPORTS[module]
                     if is_third_party(name) and top_level(name) not in RUNTIME_THIRD_PARTY | {"popcode_runtime"})
    assert not outside, f"{module} imports {outside}: the runtime installs with numpy, onnxruntime and OpenCV only"


def test_rooms_import_only_the_rooms_below_them():
    wrong = against_the_order(TRAINER_IMPORTS, TRAINER_ROOMS)
    for source, target in trainer_arrows():
        if room_of(source) == room_of(target) == "eval":
            source_part, target_part = source.split(".")[2], target.split(".")[2]
            if target_part in EVAL_PARTS and source_part in EVAL_PARTS and \
                    EVAL_PARTS.index(target_part) > EVAL_PARTS.index(source_part):
                wrong.append(f"{source} -> {target}")
    assert not wrong, "arrows against docs/architecture.md's layering:\n" + "\n".join(wrong)


def test_data_never_imports_eval():
    wrong = [f"{s} -> {t}" for s, t in trainer_arrows() if room_of(s) == "data" and room_of(t) == "eval"]
    assert not wrong, wrong


def test_metrics_are_a_pure_numpy_leaf():
    wrong = []
    for module, targets in TRAINER_IMPORTS.items():
        if room_of(module) != "metrics":
            continue
        for name in sorted(targets):
            trainer_outside = name in TRAINER_MODULES and room_of(name) != "metrics"
            third_party = is_third_party(name) and top_level(name) not in METRICS_THIRD_PARTY | {"popcode_trainer"}
            if trainer_outside or third_party:
                wrong.append(f"{module} -> {name}")
    assert not wrong, "the metrics need numpy, scipy, pycocotools and the runtime's maths only:\n" + "\n".join(wrong)


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of the graph (as the modules around it), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def package_graph(imports: dict[str, set[str]]) -> dict[str, set[str]]:
    """Module -> the modules of the same package it imports (a package's ``__init__`` is not an arrow to its
    modules: importing ``a.b`` runs ``a/__init__`` first, which is not a cycle)."""
    modules = set(imports)
    return {source: {t for t in targets if t in modules and t != source and not source.startswith(t + ".")}
            for source, targets in imports.items()}


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


@pytest.mark.parametrize("imports", [RUNTIME_IMPORTS, TRAINER_IMPORTS], ids=["runtime", "trainer"])
def test_no_import_cycles(imports):
    cycle = find_cycle(package_graph(imports))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)
