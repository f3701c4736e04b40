"""bench/ measures, experiments/ trains recipes to compare, tools/ holds what they and the tests share: held by a test
so that it cannot drift.

Every import statement is read (function-level ones too). No test imports bench or experiments: a test runs them
as a user does (``python -m bench.<name>``) or imports what it checks from tools, so that a benchmark or an
experiment may change inside without breaking a test. Between the three the imports go downward only:
experiments may import bench and tools, bench may import tools, tools neither; and no module takes a private name
(``_name``) from another.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"
# Lowest first: a package may import the packages before it, never one after it.
PACKAGES = ("tools", "bench", "experiments")
NOT_FOR_TESTS = {"bench", "experiments"}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> list[tuple[str, list[str]]]:
    """(absolute module, names taken from it) of every import statement of ``path``; a relative import is resolved
    against the package the file is in."""
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    found: list[tuple[str, list[str]]] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            source = ".".join(base + ([node.module] if node.module else []))
            found.append((source, [alias.name for alias in node.names]))
    return found


def top_level(module: str) -> str:
    return module.split(".")[0]


def package_files(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


TEST_FILES = sorted(TESTS.rglob("*.py"))
PACKAGE_FILES = [path for package in PACKAGES for path in package_files(package)]


def test_the_layout_reads_every_file():
    # A reader that found nothing would let every rule below pass.
    assert {"bench.latency", "experiments.budget_curve", "tools.fuzz_run"} <= {module_name(p) for p in PACKAGE_FILES}
    assert ("tools.command", ["run_command"]) in imports(ROOT / "bench" / "latency.py")
    assert ("experiments.budget_curve", ["curve"]) in imports(ROOT / "experiments" / "precision.py")
    assert len(TEST_FILES) > 50 and any(top_level(m) == "tools" for p in TEST_FILES for m, _ in imports(p))


@pytest.mark.parametrize("path", TEST_FILES, ids=lambda path: str(path.relative_to(TESTS)))
def test_no_test_imports_bench_or_experiments(path: Path):
    wrong = sorted({module for module, _ in imports(path) if top_level(module) in NOT_FOR_TESTS})
    assert not wrong, (f"{path.relative_to(ROOT)} imports {wrong}: run it as a user does "
                       "(`python -m bench.<name>`) or import what the test needs from tools")


@pytest.mark.parametrize("path", TEST_FILES, ids=lambda path: str(path.relative_to(TESTS)))
def test_no_test_imports_another_test_module(path: Path):
    # what tests share lives in helper modules (tests/onnx_models.py, tests/readme_text.py, ...), so that a test
    # module can be renamed or removed without breaking another
    wrong = sorted({module for module, _ in imports(path) if module.split(".")[-1].startswith("test_")})
    assert not wrong, f"{path.relative_to(ROOT)} imports test modules {wrong}: move what it needs to a helper module"


def upward(imported: dict[str, set[str]]) -> list[str]:
    """``importer -> imported`` for each import of a package that comes after the importer's in :data:`PACKAGES`."""
    rank = {package: index for index, package in enumerate(PACKAGES)}
    return [f"{source} -> {target}" for source, targets in sorted(imported.items()) for target in sorted(targets)
            if top_level(target) in rank and rank[top_level(target)] > rank[top_level(source)]]


def test_upward_finds_an_import_against_the_order():
    imported = {"tools.fuzz": {"bench.report", "tools.command", "numpy"}, "bench.latency": {"tools.report"},
                "experiments.precision": {"bench.training", "experiments.budget_curve"}}
    assert upward(imported) == ["tools.fuzz -> bench.report"]


def test_bench_experiments_and_tools_import_only_downward():
    wrong = upward({module_name(path): {module for module, _ in imports(path)} for path in PACKAGE_FILES})
    assert not wrong, "imports against the order tools < bench < experiments:\n" + "\n".join(wrong)


@pytest.mark.parametrize("package", PACKAGES)
def test_no_module_takes_a_private_name_from_another(package: str):
    wrong = [f"{module_name(path)}: from {module} import {name}" for path in package_files(package)
             for module, names in imports(path) for name in names
             if top_level(module) in PACKAGES and name.startswith("_") and not name.startswith("__")]
    assert not wrong, "private names used across modules (make them public or move them):\n" + "\n".join(wrong)


COMMANDS = [path for path in PACKAGE_FILES if 'if __name__ == "__main__":' in path.read_text(encoding="utf-8")]


@pytest.mark.parametrize("path", COMMANDS, ids=module_name)
def test_a_command_reports_bad_input_under_the_name_it_is_run_by(path: Path):
    """``run_command("bench.latency", main)``: the one line of a refusal starts with what the user typed."""
    names = {node.args[0].value for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
             if isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("run_command", "bad_input_exits")
             and node.args and isinstance(node.args[0], ast.Constant)}
    assert names == {module_name(path)}
