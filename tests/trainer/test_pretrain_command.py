"""``popcode-train pretrain``: generated parts rendered and trained into a start file with its card, resumed by the
same command, shipped where train.init 'auto' finds it, and bad options refused in one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from popcode_runtime.base.files import read_json
from popcode_trainer.cli import main
from popcode_trainer.commands import demo as demo_command
from popcode_trainer.data.generated_parts import kinds_of
from popcode_trainer.demo.steps import SMALL_NETWORK
from popcode_trainer.train import pretrained
from popcode_trainer.train.network import NetworkConfig
from popcode_trainer.train.pretrained import read_start, resolve_start, shipped_path

SMALL = ["--parts", "4", "--images", "12", "--scenes", "2", "--epochs", "2"]


@pytest.fixture(scope="module")
def pretrained_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pretrain") / "run"
    assert main(["pretrain", "--out", str(out), *SMALL]) == 0
    return out


@pytest.mark.slow
def test_the_start_and_its_card(pretrained_run: Path) -> None:
    start = read_start(pretrained_run / "pretrained-start.pt")
    card = start.card
    assert card["parts"] == 4 and card["epochs"] == 2 and card["images_per_part"] == 12 and card["scenes"] == 2
    assert sum(card["kinds"].values()) == 4 and set(card["kinds"]) <= {"discrete", "none", "look_alike"}
    assert card["commit"] and card["training_seconds"] > 0 and 0 <= card["val_error_median_deg"] <= 180
    assert set(kinds_of(pretrained_run / "parts").values()) <= {"discrete", "none", "look_alike"}
    assert start.network["conv_channels"] == list(SMALL_NETWORK.conv_channels)
    assert read_json(pretrained_run / "run" / "start.json")["init"] == "none"  # the pretraining itself starts random


def test_a_rerun_resumes_and_another_part_count_is_refused(pretrained_run: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    before = (pretrained_run / "run" / "last.pt").stat().st_mtime_ns
    assert main(["pretrain", "--out", str(pretrained_run), *SMALL]) == 0
    assert (pretrained_run / "run" / "last.pt").stat().st_mtime_ns == before  # nothing trained again
    assert main(["pretrain", "--out", str(pretrained_run), *SMALL[:1], "5", *SMALL[2:]]) == 2
    assert "started with 4 parts, not 5" in capsys.readouterr().err


def test_ship_puts_it_where_auto_finds_it(pretrained_run: Path, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pretrained, "SHIPPED_DIR", tmp_path)
    assert main(["pretrain", "--out", str(pretrained_run), *SMALL, "--ship"]) == 0
    network = NetworkConfig(**{**SMALL_NETWORK.__dict__, "output_dim": 1})
    assert shipped_path(network).is_file()
    start, line = resolve_start("auto", network)
    assert start is not None and "4 generated parts" in line


@pytest.mark.parametrize(("option", "value"), [("--parts", "0"), ("--images", "-3"), ("--epochs", "1"),
                                               ("--minutes", "nan"), ("--scenes", "-1")])
def test_bad_options_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str) -> None:
    assert main(["pretrain", "--out", str(tmp_path / "run"), option, value]) == 2
    err = capsys.readouterr().err
    assert option in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(("options", "init"), [([], "auto"), (["--from-scratch"], "none")])
def test_demo_starts_from_the_shipped_start_unless_told(options: list[str], init: str,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    seen = []
    monkeypatch.setattr(demo_command, "run_demo", lambda name, out, size, **kwargs: seen.append(size))
    assert main(["demo", "--out", "unused", *options]) == 0
    assert seen[0].config.train.init == init


def test_train_refuses_a_start_of_another_network_before_reading_data(pretrained_run: Path, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    start = pretrained_run / "pretrained-start.pt"
    assert main(["train", "--set", f'train.init="{start}"', "--set", f'data.splits=["{tmp_path / "none"}"]']) == 2
    err = capsys.readouterr().err.strip()
    assert "was pretrained for another network (network.conv_channels" in err and len(err.splitlines()) == 1
