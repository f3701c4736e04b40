"""The README's commands are real: every command line parses with the CLI it names, every file and
link it points to exists, and the shipped-model commands run as written."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from popcode_runtime.commands.cli import build_parser as runtime_parser
from popcode_runtime.commands.cli import main as runtime_main
from popcode_trainer.cli import build_parser as trainer_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
REPO_PATH = re.compile(r"^(models|trainer|bench|docs|runtime|tests)/[\w./-]+$")


def bash_commands(markdown: str) -> list[list[str]]:
    """Every command of the ```bash blocks, continuation lines joined, comments dropped, split like a shell."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", markdown, flags=re.DOTALL):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words:
                commands.append(words)
    return commands


COMMANDS = bash_commands(README)
INLINE_BENCH = re.findall(r"`python -m (bench\.\w+)([^`]*)`", README)


def _ids(commands: list[list[str]]) -> list[str]:
    return [" ".join(words)[:60] for words in commands]


def test_the_readme_has_the_commands_it_should() -> None:
    programs = {words[0] for words in COMMANDS}
    assert {"make", "popcode", "popcode-train", "torchrun", "pip"} <= programs
    assert ["make", "demo"] in COMMANDS and ["make", "test"] in COMMANDS
    assert len(INLINE_BENCH) >= 4


@pytest.mark.parametrize("words", COMMANDS, ids=_ids(COMMANDS))
def test_command_parses(words: list[str]) -> None:
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
        assert args[0] == "install" and (ROOT / args[1]).is_dir()
    else:
        pytest.fail(f"the README runs {program!r}, which no test checks")
    for word in args:
        if REPO_PATH.match(word) and not word.startswith(("runs/", "data/")):
            assert (ROOT / word).exists(), f"{word} does not exist"


def test_ci_runs_exactly_the_readme_test_command() -> None:
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line and not line.startswith("#")]
    assert ci[-1] == "make test"


def test_links_and_images_exist() -> None:
    targets = re.findall(r"\]\(([^)#]+)\)", README)
    assert targets
    for target in targets:
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target


@pytest.mark.parametrize("module, options", INLINE_BENCH)
def test_bench_commands_parse(module: str, options: str) -> None:
    result = subprocess.run([sys.executable, "-m", module, *shlex.split(options), "--help"],
                            capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr


def test_shipped_model_commands_run(capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    shipped = [words for words in COMMANDS if words[0] == "popcode" and words[2].startswith("models/")
               and not any(w.startswith(("runs/", "data/")) for w in words)]  # those need the reader's own data
    assert len(shipped) >= 3
    for words in shipped:
        args = [str(ROOT / w) if REPO_PATH.match(w) else w for w in words[1:]]
        shown = made = None
        if "--draw" in args:  # not over the README's picture: beside it, then compared with it
            value = args.index("--draw") + 1
            shown, made = Path(args[value]), tmp_path / Path(args[value]).name
            args[value] = str(made)
        assert runtime_main(args) == 0, " ".join(words)
        if shown is not None:
            assert np.array_equal(cv2.imread(str(made)), cv2.imread(str(shown))), f"{shown} is not what it draws"
    predicts = sum(words[1] == "predict" for words in shipped)
    assert capsys.readouterr().out.count("box 0 [") == predicts
