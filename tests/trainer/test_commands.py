"""The command line: named errors for bad configs, and export from a checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from trained import trained_checkpoint

from popcode_runtime.base.errors import PopcodeError
from popcode_trainer.cli import main
from popcode_trainer.train.config import Config, load_config


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.toml"
    path.write_text(text)
    return path


def test_defaults_are_the_papers() -> None:
    config = load_config()
    assert (config.train.lr, config.train.batch_size, config.train.epochs) == (2e-4, 64, 80)
    assert (config.code.n_axes, config.code.n_angles, config.code.sigma_deg) == (2562, 36, 20.0)
    assert Config.from_dict(config.to_dict()) == config


def test_overrides_are_typed(tmp_path: Path) -> None:
    path = write(tmp_path, '[train]\nlr = 1e-3\n[data]\nobj_ids = [5, 6]\nsplits = ["a", "b"]\n')
    config = load_config(path, ["train.epochs=3", "train.out_dir=runs/x", "network.hidden=[64, 32, 16]"])
    assert config.train.epochs == 3 and config.train.out_dir == str(Path.cwd() / "runs" / "x")
    assert config.train.lr == 1e-3 and config.data.obj_ids == (5, 6) and config.network.hidden == (64, 32, 16)


def test_paths_in_a_config_are_relative_to_its_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The file's paths from its folder, --set paths from the current folder, both stored absolute (issue 19)."""
    (tmp_path / "configs").mkdir()
    path = tmp_path / "configs" / "run.toml"
    path.write_text('[data]\nsplits = ["../data/a", "/abs/b"]\nmodels_dir = "models"\n[train]\nout_dir = "runs/x"\n')
    monkeypatch.chdir(tmp_path.parent)
    config = load_config(path, ['data.models_dir="elsewhere/models"'])
    assert config.data.splits == (str(tmp_path / "data" / "a"), "/abs/b")
    assert config.data.models_dir == str(tmp_path.parent / "elsewhere" / "models")
    assert config.train.out_dir == str(tmp_path / "configs" / "runs" / "x")
    assert load_config(path).data.models_dir == str(tmp_path / "configs" / "models")


@pytest.mark.parametrize(("text", "overrides", "message"), [
    ("[train]\nlearning_rate = 1e-3\n", [], r"train.learning_rate.*valid keys in \[train\].*'lr'"),
    ("[trian]\n", [], r"\['trian'\].*valid sections"),
    ('[train]\nrepresentation = "quaternion"\n', [], r"'quaternion'.*'population_code'"),
    ("", ["train.rotation_frame=world"], r"'world'.*'egocentric', 'allocentric'"),
    ("", ["train.epochs=many"], r"train.epochs must be int"),
    ("", ["network.output_dim=10"], r"network.output_dim"),
    ("", ["trainlr=1"], r"section.key=value"),
])
def test_bad_settings_are_named(tmp_path: Path, text: str, overrides: list[str], message: str) -> None:
    with pytest.raises(PopcodeError, match=message):
        load_config(write(tmp_path, text), overrides)


def test_cli_reports_bad_config_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, "[train]\nlearning_rate = 1e-3\n")
    assert main(["train", "--config", str(path)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("popcode-train: error: unknown config key") and "\n" not in error


def test_export_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ckpt, crops = trained_checkpoint(tmp_path)
    np.save(tmp_path / "crops.npy", crops)
    out = tmp_path / "model.onnx"
    capsys.readouterr()  # the training's log
    assert main(["export", str(ckpt), "--out", str(out), "--crops", str(tmp_path / "crops.npy"),
                 "--quantize", "int8", "--split-output", "256"]) == 0
    assert out.is_file() and (tmp_path / "model.int8.onnx").is_file()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[-4:] == ["argmax", "agreement", "pose", "agreement"]
    for line, name in zip(lines[1:3], ("model.onnx", "model.int8.onnx"), strict=True):
        assert line.split()[0].endswith(name) and line.split()[-1].endswith("%")  # one object: pose measured
    assert lines[1].split()[-2:] == ["100.0%", "100.0%"]  # onnxruntime vs torch
    np.save(tmp_path / "ids.npy", np.full(len(crops), 7))
    again = ["export", str(ckpt), "--out", str(out), "--crops", str(tmp_path / "crops.npy"), "--quantize", "int8"]
    assert main(again) == 2 and "model.onnx exists already; pass --overwrite" in capsys.readouterr().err
    out.unlink()  # the quantised copy is an output too
    assert main(again) == 2 and "model.int8.onnx exists already; pass --overwrite" in capsys.readouterr().err
    assert main(["export", str(ckpt), "--out", str(out), "--crops", str(tmp_path / "crops.npy"),
                 "--crop-obj-ids", str(tmp_path / "ids.npy")]) == 2
    assert "object ids [7] are not in this model" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "missing.pt"), "--out", str(out), "--crops",
                 str(tmp_path / "crops.npy")]) == 2


def test_shipped_config_parses() -> None:
    repository = Path(__file__).resolve().parents[2]
    config = load_config(repository / "trainer" / "configs" / "paper.toml")
    assert config.data.obj_ids == (5, 6) and config == Config.from_dict(config.to_dict())
    # The README's layout, from the repository root: data/tless/..., runs/tless_05_06_popcode/last.pt.
    assert config.data.models_dir == str(repository / "data" / "tless" / "models")
    assert config.train.out_dir == str(repository / "runs" / "tless_05_06_popcode")
