"""The README's commands are real: every command line parses with the CLI it names, every file and link it points
to exists, and every runtime example and Python snippet runs as written against the shipped models.

The same holds for the runtime's own readme (runtime/README.md) and the pages of docs/: their command lines
parse, and their runtime examples run. Only examples that need the reader's own data (paths under ``runs/`` or
``data/``) are parsed without running.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from readme_text import README, bash_commands

from popcode_runtime import FramePose, Prediction
from popcode_runtime.commands.cli import build_parser as runtime_parser
from popcode_runtime.commands.cli import main as runtime_main
from popcode_runtime.geometry.rotations import is_rotation
from popcode_trainer.cli import build_parser as trainer_parser

ROOT = Path(__file__).resolve().parents[1]
RUNTIME_README = (ROOT / "runtime" / "README.md").read_text()
DOC_PAGES = {str(page.relative_to(ROOT)): page.read_text() for page in sorted((ROOT / "docs").glob("*.md"))}
REPO_PATH = re.compile(r"^(models|trainer|bench|docs|runtime|tests|experiments|tools)/[\w./-]+$")
OWN_DATA = ("runs/", "data/")  # the reader's own splits and runs: parsed, not run
MODULE_COMMAND = r"python -m ((?:bench|experiments|tools)\.\w+)"


def python_snippets(markdown: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", markdown, flags=re.DOTALL)


COMMANDS = bash_commands(README)
INLINE_BENCH = re.findall(rf"`{MODULE_COMMAND}([^`]*)`", README)
# Every page's commands, each with the page it comes from.
PAGES = {"README.md": README, "runtime/README.md": RUNTIME_README, **DOC_PAGES}
ALL_COMMANDS = [(page, words) for page, text in PAGES.items() for words in bash_commands(text)]
RUNTIME_EXAMPLES = [(page, words) for page, words in ALL_COMMANDS if words[0] == "popcode"
                    and not any(word.startswith(OWN_DATA) for word in words)]
SNIPPETS = [(page, code) for page in ("README.md", "runtime/README.md") for code in python_snippets(PAGES[page])]


def _ids(commands: list[tuple[str, list[str]]]) -> list[str]:
    return [f"{page}: {' '.join(words)[:60]}" for page, words in commands]


def test_the_readme_has_the_commands_it_should() -> None:
    programs = {words[0] for words in COMMANDS}
    assert {"make", "popcode", "popcode-train", "torchrun", "pip"} <= programs
    assert ["make", "demo"] in COMMANDS and ["make", "test"] in COMMANDS
    assert len(INLINE_BENCH) >= 4
    assert python_snippets(README) and python_snippets(RUNTIME_README)
    assert len(README.splitlines()) <= 350, "the README is read in ten minutes; details go to docs/"


def test_the_results_show_today_on_two_screens() -> None:
    """The Results are today's figures, one table a block, each block dated; older runs live in
    bench/results/readme-history.md, so the section cannot grow into a logbook again."""
    results = README.split("\n## Results\n", 1)[1].split("\n## ", 1)[0]
    assert len(results.splitlines()) <= 60
    blocks = [block for block in results.split("\n\n") if block.startswith("**")]
    assert len(blocks) >= 3
    for block in blocks:
        assert re.search(r"\b20\d\d-\d\d-\d\d\b", block), f"undated results: {block[:60]}"
    tables = [block for block in results.split("\n\n") if block.startswith("|")]
    assert len(tables) == len(blocks), "one table for each block of results"


@pytest.mark.parametrize("page, words", ALL_COMMANDS, ids=_ids(ALL_COMMANDS))
def test_command_parses(page: str, words: list[str]) -> None:
    program, args = words[0], words[1:]
    if program == "popcode":
        runtime_parser().parse_args(args)
    elif program == "popcode-train":
        trainer_parser().parse_args(args)
    elif program == "torchrun":
        module = args.index("-m")
        assert args[module + 1] == "popcode_trainer.cli"
        trainer_parser().parse_args(args[module + 2:])
    elif program == "make":
        assert re.search(rf"^{re.escape(args[0])}:", (ROOT / "Makefile").read_text(), flags=re.MULTILINE)
    elif program == "pip":
        assert args[0] == "install" and (ROOT / args[1].split("[")[0]).is_dir()
    else:
        pytest.fail(f"{page} runs {program!r}, which no test checks")
    for word in args:
        if REPO_PATH.match(word) and not word.startswith(OWN_DATA):
            assert (ROOT / word).exists(), f"{page}: {word} does not exist"


def test_ci_runs_exactly_the_readme_test_command() -> None:
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line and not line.startswith("#")]
    assert ci[-1] == "make test"


@pytest.mark.parametrize("page", ["README.md", "runtime/README.md"])
def test_links_and_images_exist(page: str) -> None:
    targets = re.findall(r"\]\(([^)#]+)\)", PAGES[page])
    assert targets
    for target in targets:
        if not target.startswith("http"):
            assert ((ROOT / page).parent / target).exists(), f"{page}: {target}"


# ``python -c`` this with a JSON list of [module, *options]: ``python -m module options --help`` for each, in one
# process, so that torch and the rest are imported once, not once a command; prints [exit status, stderr] of each.
HELP_EACH = """import contextlib, io, json, runpy, sys, traceback
answers = []
for module, *options in json.loads(sys.argv[1]):
    sys.argv, err, status = [module, *options, "--help"], io.StringIO(), 0
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as stop:
        status = stop.code if isinstance(stop.code, int) or stop.code is None else str(stop.code)
    except Exception:
        status = traceback.format_exc()
    answers.append([status or 0, err.getvalue()])
print(json.dumps(answers))
"""


@pytest.fixture(scope="module")
def bench_helps() -> dict[tuple[str, str], list]:
    """Each of the README's benchmark commands with ``--help``, as ``python -m`` runs it, all in one process."""
    commands = [[module, *shlex.split(options)] for module, options in INLINE_BENCH]
    done = subprocess.run([sys.executable, "-c", HELP_EACH, json.dumps(commands)], capture_output=True, text=True,
                          cwd=ROOT)
    assert done.returncode == 0, done.stderr
    return dict(zip(INLINE_BENCH, json.loads(done.stdout.splitlines()[-1]), strict=True))


@pytest.mark.parametrize("module, options", INLINE_BENCH)
def test_bench_commands_parse(module: str, options: str, bench_helps: dict[tuple[str, str], list]) -> None:
    status, stderr = bench_helps[module, options]
    assert status == 0, stderr


def test_the_docs_name_modules_that_exist() -> None:
    # the pages of docs/ list many more benchmark commands than the README; that each module is there is checked
    # here, cheaply (the README's own are run with --help above)
    named = {module for text in DOC_PAGES.values() for module in re.findall(MODULE_COMMAND, text)}
    assert named
    missing = sorted(module for module in named if not (ROOT / (module.replace(".", "/") + ".py")).is_file())
    assert not missing, f"docs/ runs modules that do not exist: {missing}"


def test_every_runtime_example_without_own_data_runs() -> None:
    # the filter leaves out only what needs the reader's own data: the README's own examples all run
    readme_examples = [words for page, words in RUNTIME_EXAMPLES if page == "README.md"]
    assert len(readme_examples) >= 5
    assert {words[1] for words in readme_examples} >= {"info", "predict", "bench"}
    left_out = [words for words in COMMANDS if words[0] == "popcode" and words not in readme_examples]
    assert all(any(word.startswith(OWN_DATA) for word in words) for words in left_out)


@pytest.mark.parametrize("page, words", RUNTIME_EXAMPLES, ids=_ids(RUNTIME_EXAMPLES))
def test_runtime_example_runs(page: str, words: list[str], capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    args = [str(ROOT / w) if REPO_PATH.match(w) else w for w in words[1:]]
    shown = made = None
    if "--draw" in args:  # not over the page's picture: beside it, then compared with it where the repository has it
        value = args.index("--draw") + 1
        shown, made = Path(args[value]), tmp_path / Path(args[value]).name
        args[value] = str(made)
    capsys.readouterr()
    assert runtime_main(args) == 0, f"{page}: {' '.join(words)}"
    out = capsys.readouterr().out
    if made is not None:
        assert cv2.imread(str(made)) is not None, f"{page}: no picture drawn"
        if shown.is_file():
            assert np.array_equal(cv2.imread(str(made)), cv2.imread(str(shown))), f"{shown} is not what it draws"
    if words[1] == "predict" and "--json" in words:
        predictions = json.loads(out)["predictions"]
        assert len(predictions) == words.count("--box")
        assert all(is_rotation(np.asarray(p["R_m2c"])) for p in predictions)
    elif words[1] == "predict":
        assert out.count("box 0 [") == 1, out
        assert "skipped" not in out, out  # with --detector: every box the detector finds gets a pose
    elif words[1] == "info":
        assert "representation" in out and "rotation frame" in out
    elif words[1] == "bench":
        assert "median ms" in out


def _printed_matrix(text: str) -> np.ndarray:
    """The first 3x3 matrix a snippet prints (numpy's text form)."""
    numbers = re.findall(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?", text)
    assert len(numbers) >= 9, f"the snippet printed no rotation matrix: {text!r}"
    return np.array([float(n) for n in numbers[:9]]).reshape(3, 3)


@pytest.mark.parametrize("page, code", SNIPPETS, ids=[page for page, _ in SNIPPETS])
def test_python_snippet_runs(page: str, code: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # as written, from a folder that holds the repository's models/ (what the snippet's relative paths name) and
    # nothing else, so that whatever it might write lands there
    os.symlink(ROOT / "models", tmp_path / "models")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__readme__"}
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(code, f"<{page}>", "exec"), namespace)  # noqa: S102 - the snippet is the repository's own text
    predictions = [value for value in namespace.values() if isinstance(value, Prediction)]
    predictions += [value.prediction for value in namespace.values() if isinstance(value, FramePose)]
    predictions += [item for value in namespace.values() if isinstance(value, list)
                    for item in value if isinstance(item, Prediction)]
    assert predictions, f"{page}'s snippet keeps no Prediction to check"
    assert all(is_rotation(p.R_m2c) for p in predictions)
    assert is_rotation(_printed_matrix(printed.getvalue()), atol=1e-3)  # as printed: a few digits
