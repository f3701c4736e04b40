"""Pretrained starts (train.pretrained): written and read back, copied into a network of the same shape whatever its
code, taken by training through train.init, and every file that is not a start of this network refused in one line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from tiny import tiny_config, tiny_data, tiny_representation

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json
from popcode_trainer.train import checkpoint, pretrained
from popcode_trainer.train.loop import network_config, train
from popcode_trainer.train.network import NetworkConfig, build_network
from popcode_trainer.train.pretrained import (
    START_VERSION,
    apply_start,
    read_start,
    resolve_start,
    shipped_path,
    write_start,
)
from popcode_trainer.train.run_files import LAST_CHECKPOINT, START_FILE

TINY = NetworkConfig(output_dim=42 * 12, input_size=128, conv_channels=(8, 8, 8), squeeze_channels=4,
                     hidden=(32, 32, 32))
CARD = {"parts": 5, "epochs": 2, "commit": "abc1234"}


def _start(folder: Path, config: NetworkConfig = TINY) -> tuple[Path, torch.nn.Module]:
    torch.manual_seed(3)
    model = build_network(config)
    return write_start(model, config, folder / "start.pt", CARD), model


def _transferred(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v for k, v in model.state_dict().items() if k.split(".")[0] in ("features", "hidden")}


def test_a_start_fills_the_trunk_of_a_network_with_another_code(tmp_path: Path) -> None:
    path, source = _start(tmp_path)
    start = read_start(path)
    assert start.card == CARD and "output_dim" not in start.network
    other_code = dataclasses.replace(TINY, output_dim=642 * 36)
    torch.manual_seed(4)
    target = build_network(other_code)
    head_before = target.head.weight.detach().clone()
    assert apply_start(target, start, other_code) == len(_transferred(source))
    for name, tensor in _transferred(source).items():
        torch.testing.assert_close(target.state_dict()[name], tensor, msg=name)
    torch.testing.assert_close(target.head.weight, head_before)  # the output layer is each model's own


def test_a_start_of_another_network_shape_is_refused_naming_the_difference(tmp_path: Path) -> None:
    path, _ = _start(tmp_path)
    wider = dataclasses.replace(TINY, conv_channels=(8, 16, 8))
    with pytest.raises(PopcodeError, match=r"pretrained for another network \(network.conv_channels \[8, 8, 8\] there, "
                                           r"\[8, 16, 8\] here\)"):
        resolve_start(str(path), wider)
    with pytest.raises(PopcodeError, match="network.input_size"):
        apply_start(build_network(dataclasses.replace(TINY, input_size=64)), read_start(path),
                    dataclasses.replace(TINY, input_size=64))


@pytest.mark.parametrize("damage", ["truncated", "random bytes", "empty"])
def test_a_damaged_start_is_refused_in_one_line(tmp_path: Path, damage: str) -> None:
    path, _ = _start(tmp_path)
    data = path.read_bytes()
    path.write_bytes({"truncated": data[:len(data) // 2], "random bytes": bytes(range(256)) * 40, "empty": b""}[damage])
    with pytest.raises(PopcodeError, match="cannot read checkpoint") as caught:
        read_start(path)
    assert "\n" not in str(caught.value)


def test_files_that_are_not_starts_of_this_trainer_are_refused(tmp_path: Path) -> None:
    path, model = _start(tmp_path)
    state = checkpoint.load(path)
    newer = tmp_path / "newer.pt"
    checkpoint.save_atomic({**state, "version": START_VERSION + 1}, newer)
    with pytest.raises(PopcodeError, match="newer than this trainer reads"):
        read_start(newer)
    config = tiny_config(tmp_path / "run", epochs=1, init="none")
    representation = tiny_representation(config)
    train(config, representation, *tiny_data(representation))
    with pytest.raises(PopcodeError, match="is not a pretrained start"):
        read_start(tmp_path / "run" / LAST_CHECKPOINT)  # a training checkpoint
    wrong = tmp_path / "wrong.pt"
    checkpoint.save_atomic({**state, "state": {**state["state"], "features.0.weight": torch.zeros(1)}}, wrong)
    with pytest.raises(PopcodeError, match="do not fit"):
        apply_start(build_network(TINY), read_start(wrong), TINY)
    with pytest.raises(PopcodeError, match="pretrained start not found"):
        resolve_start(str(tmp_path / "missing.pt"), TINY)


def test_auto_takes_the_shipped_start_of_the_network_or_says_there_is_none(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pretrained, "SHIPPED_DIR", tmp_path)
    start, line = resolve_start("auto", TINY)
    assert start is None and line.startswith("random weights: no pretrained start is shipped")
    path, _ = _start(tmp_path)
    path.rename(shipped_path(TINY, tmp_path))
    start, line = resolve_start("auto", TINY)
    assert start is not None and "the shipped pretrained start" in line and "5 generated parts" in line
    assert resolve_start("none", TINY) == (None, "random weights (train.init 'none')")


def test_training_starts_from_the_start_and_records_it(tmp_path: Path) -> None:
    config = tiny_config(tmp_path / "run", epochs=1, lr=1e-12, init="")
    representation = tiny_representation(config)
    net_config = network_config(config, representation)
    path, source = _start(tmp_path, net_config)
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, init=str(path)))
    train(config, representation, *tiny_data(representation))
    trained = checkpoint.load(tmp_path / "run" / LAST_CHECKPOINT)["model"]
    for name, tensor in source.named_parameters():  # a rate of 1e-12 leaves the start's weights where they were
        if name.split(".")[0] in ("features", "hidden"):
            torch.testing.assert_close(trained[name], tensor.detach(), atol=1e-6, rtol=0, msg=name)
    record = read_json(tmp_path / "run" / START_FILE)
    assert record["path"] == str(path) and record["card"] == CARD and str(path) in record["start"]


def test_a_start_learns_at_its_own_rate_when_asked(tmp_path: Path) -> None:
    config = tiny_config(tmp_path / "run", epochs=1, init="", init_lr_scale=0.25, lr=1e-3)
    representation = tiny_representation(config)
    path, _ = _start(tmp_path, network_config(config, representation))
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, init=str(path)))
    train(config, representation, *tiny_data(representation))
    groups = checkpoint.load(tmp_path / "run" / LAST_CHECKPOINT)["optimizer"]["param_groups"]
    assert [group["lr_scale"] for group in groups] == [0.25, 1.0]
    assert groups[0]["lr"] == pytest.approx(0.25 * groups[1]["lr"])
    scratch = dataclasses.replace(config, train=dataclasses.replace(config.train, init="none",
                                                                    out_dir=str(tmp_path / "scratch")))
    train(scratch, representation, *tiny_data(representation))  # no start: every weight at the run's rate
    groups = checkpoint.load(tmp_path / "scratch" / LAST_CHECKPOINT)["optimizer"]["param_groups"]
    assert [group["lr_scale"] for group in groups] == [1.0, 1.0]
