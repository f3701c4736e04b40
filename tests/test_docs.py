"""The documentation points at what exists: docs/architecture.md names every module of both packages, and every
repository path that a docstring or a page of docs/ cites is there (with its anchor, where it names one).

The packages are walked when the test runs, so a module added, moved or split is caught the day it appears.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
ARCHITECTURE = (DOCS / "architecture.md").read_text(encoding="utf-8")
PACKAGES = (ROOT / "runtime" / "popcode_runtime", ROOT / "trainer" / "popcode_trainer")
# Folders whose Python files' docstrings may cite repository paths (those that exist today).
SOURCE_FOLDERS = [ROOT / name for name in ("runtime", "trainer", "tests", "bench", "experiments", "tools")
                  if (ROOT / name).is_dir()]
# A path as the docs and docstrings cite one: a .py or .md file under one of the repository's top folders,
# maybe with an anchor; not the tail of a longer path (``../bench/...`` in a link is read as a link instead).
CITED = re.compile(r"(?<![\w/.-])((?:runtime|trainer|docs|bench|models|tests|experiments|tools)/[\w./-]*?\.(?:py|md))"
                   r"(?:#([\w-]+))?(?![\w/-])")
LINK = re.compile(r"\]\(([^)\s]+)\)")
# Paths of other projects that a docstring names in passing: the BOP toolkit's format spec.
ELSEWHERE = {"docs/bop_datasets_format.md"}


def module_names(package_dir: Path) -> dict[str, Path]:
    """Dotted name -> file of every module of a package (``__init__`` as the package's own name)."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


MODULES = {name: path for package in PACKAGES for name, path in module_names(package).items()}


def named(name: str, path: Path, text: str) -> bool:
    """Whether ``text`` names the module: its whole dotted name (``...commands.run`` is not ``...commands.run_loop``)
    or its file's path."""
    as_name = re.search(rf"(?<![\w.]){re.escape(name)}(?!\w)", text)
    return bool(as_name) or path.relative_to(ROOT).as_posix() in text


def anchors(page: Path) -> set[str]:
    """The anchors of a markdown page: explicit ``<a id="...">`` ones and GitHub's heading slugs."""
    text = page.read_text(encoding="utf-8")
    explicit = set(re.findall(r'<a id="([\w-]+)">', text))
    slugs = {re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
             for heading in re.findall(r"^#+ (.*)$", text, flags=re.MULTILINE)}
    return explicit | slugs


def docstrings(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = [tree, *(node for node in ast.walk(tree)
                     if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)))]
    return [text for node in nodes if (text := ast.get_docstring(node, clean=False))]


# Folders of built or installed copies, not sources (``pip install ./runtime`` leaves runtime/build/).
NOT_SOURCES = {".venv", "build", "dist", "site-packages", "__pycache__"}


def python_files() -> list[Path]:
    return sorted(path for folder in SOURCE_FOLDERS for path in folder.rglob("*.py")
                  if not NOT_SOURCES & set(path.relative_to(ROOT).parts)
                  and not any(part.endswith(".egg-info") for part in path.parts))


def cited_in_docstrings() -> list[tuple[str, str, str | None]]:
    """(where, path, anchor) of every repository path a docstring cites."""
    return [(str(source.relative_to(ROOT)), cited, anchor)
            for source in python_files() for text in docstrings(source)
            for cited, anchor in CITED.findall(text) if cited not in ELSEWHERE]


def cited_in_docs() -> list[tuple[str, Path, str | None]]:
    """(where, file, anchor) of every path a page of docs/ cites: in its text from the repository root, as a link
    target from the page's folder."""
    found = []
    for page in sorted(DOCS.glob("*.md")):
        text = page.read_text(encoding="utf-8")
        where = str(page.relative_to(ROOT))
        found += [(where, ROOT / cited, anchor or None) for cited, anchor in CITED.findall(text)
                  if cited not in ELSEWHERE]
        for target in LINK.findall(text):
            if re.match(r"[a-z]+:", target):
                continue
            file, _, anchor = target.partition("#")
            found.append((where, (page.parent / file).resolve() if file else page, anchor or None))
    return found


def test_the_walk_finds_the_packages() -> None:
    # a walk that found nothing would let every check below pass
    assert {"popcode_runtime.inference.estimator", "popcode_trainer.train.loop"} <= set(MODULES)
    assert len(MODULES) > 100


@pytest.mark.parametrize("name", sorted(MODULES))
def test_architecture_names_every_module(name: str) -> None:
    assert named(name, MODULES[name], ARCHITECTURE), f"docs/architecture.md does not name {name}"


def test_a_name_is_not_found_inside_a_longer_one() -> None:
    module = ROOT / "runtime" / "popcode_runtime" / "commands" / "run.py"
    assert not named("popcode_runtime.commands.run", module, "`popcode_runtime.commands.run_loop`")
    assert named("popcode_runtime.commands.run", module, "`popcode_runtime.commands.run` and")
    assert named("popcode_runtime.commands.run", module, "see runtime/popcode_runtime/commands/run.py")


def test_docstrings_cite_only_what_exists() -> None:
    cited = cited_in_docstrings()
    assert any(path == "docs/design.md" for _, path, _ in cited)  # the modules that rely on the design cite it
    missing = [f"{where}: {path}" for where, path, _ in cited if not (ROOT / path).exists()]
    assert not missing, "docstrings cite paths that do not exist:\n" + "\n".join(missing)
    lost = [f"{where}: {path}#{anchor}" for where, path, anchor in cited
            if anchor and path.endswith(".md") and (ROOT / path).exists() and anchor not in anchors(ROOT / path)]
    assert not lost, "docstrings cite anchors that do not exist:\n" + "\n".join(lost)


def test_docs_cite_only_what_exists() -> None:
    cited = cited_in_docs()
    assert len(cited) > 20
    missing = [f"{where}: {path}" for where, path, _ in cited if not path.exists()]
    assert not missing, "docs/ cites paths that do not exist:\n" + "\n".join(missing)
    lost = [f"{where}: {path.name}#{anchor}" for where, path, anchor in cited
            if anchor and path.suffix == ".md" and anchor not in anchors(path)]
    assert not lost, "docs/ links to anchors that do not exist:\n" + "\n".join(lost)


def test_nothing_cites_the_design_notes_outside_the_repository() -> None:
    # DESIGN.md was never part of the repository; docs/design.md took its place
    texts = [(str(path.relative_to(ROOT)), text) for path in python_files() for text in docstrings(path)]
    texts += [(str(page.relative_to(ROOT)), page.read_text(encoding="utf-8")) for page in DOCS.glob("*.md")]
    stale = sorted({where for where, text in texts if re.search(r"\bDESIGN(\.md|\s+§|\s+section)", text)})
    assert not stale, f"cite DESIGN.md instead of docs/design.md: {stale}"


def test_every_section_of_the_design_has_a_stable_anchor() -> None:
    lines = (DOCS / "design.md").read_text(encoding="utf-8").splitlines()
    sections = [index for index, line in enumerate(lines) if line.startswith("## ")]
    assert len(sections) >= 8
    bare = [lines[index] for index in sections if not lines[index - 1].startswith('<a id="')]
    assert not bare, f"sections of docs/design.md without an <a id> anchor above them: {bare}"
