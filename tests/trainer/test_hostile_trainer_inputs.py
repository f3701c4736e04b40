"""Issue 19's catalogue for ``popcode-train``: bad files, folders and settings end in one line and exit 2."""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from hostile_cases import error_lines

from popcode_trainer.checkpoint import TRAINED_KEYS
from popcode_trainer.cli import main


class NotPlainData:
    """An object whose pickle needs this class: weights_only loading refuses it."""


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("hostile_trainer")
    (folder / "junk.pt").write_bytes(b"\x00not a checkpoint")
    torch.save(torch.zeros(3), folder / "tensor.pt")
    torch.save({"model": {}, "config": {}}, folder / "partial.pt")
    torch.save({**{key: {} for key in TRAINED_KEYS}, "metadata": [1, 2]}, folder / "list_metadata.pt")
    with (folder / "pickled.pt").open("wb") as handle:
        torch.save({"model": NotPlainData()}, handle, pickle_module=pickle)
    torch.save({**{key: {} for key in TRAINED_KEYS}, "epoch": 0, "best_val_error_deg": 0.0}, folder / "keys.pt")
    np.savez(folder / "arrays.npz", a=np.zeros(3))
    np.save(folder / "nan_crops.npy", np.full((4, 1, 128, 128), np.nan, np.float32))
    np.save(folder / "flat_crops.npy", np.zeros((4, 128, 128), np.float32))
    np.save(folder / "bright_crops.npy", np.full((4, 1, 128, 128), 3.0, np.float32))
    np.save(folder / "empty_crops.npy", np.zeros((0, 1, 128, 128), np.float32))
    np.save(folder / "good_crops.npy", np.zeros((4, 1, 128, 128), np.float32))
    np.save(folder / "object_crops.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(folder / "float_ids.npy", np.array([1.5, 2.0, 3.0, 4.0]))
    (folder / "not_npy.npy").write_text("text")
    (folder / "a_folder").mkdir()
    (folder / "config.toml").write_text("[data]\nsplits = ['nowhere']\n")
    return folder


def _export(files: Path, *extra: str, checkpoint: str = "keys.pt", out: str = "out.onnx") -> list[str]:
    return ["export", str(files / checkpoint), "--out", str(files / out), *extra]


CASES = [
    ("export-junk", lambda f: _export(f, checkpoint="junk.pt"), "cannot read checkpoint"),
    ("export-missing", lambda f: _export(f, checkpoint="missing.pt"), "checkpoint not found"),
    ("export-folder-as-checkpoint", lambda f: _export(f, checkpoint="a_folder"), "checkpoint not found"),
    ("export-tensor", lambda f: _export(f, checkpoint="tensor.pt"), "holds a Tensor"),
    ("export-partial", lambda f: _export(f, checkpoint="partial.pt"), "is not a popcode training checkpoint"),
    ("export-list-metadata", lambda f: _export(f, checkpoint="list_metadata.pt"), "are not dicts"),
    ("export-pickled", lambda f: _export(f, checkpoint="pickled.pt"), "not a trusted popcode checkpoint"),
    ("export-npz", lambda f: _export(f, checkpoint="arrays.npz"), "cannot read checkpoint"),
    ("export-out-folder", lambda f: _export(f, out="a_folder"), "is a folder"),
    ("export-out-nowhere", lambda f: _export(f, out="no/such/model.onnx"), "does not exist"),
    ("export-crops-nan", lambda f: _export(f, "--crops", str(f / "nan_crops.npy"), "--quantize", "int8"), "NaN"),
    ("export-crops-3d", lambda f: _export(f, "--crops", str(f / "flat_crops.npy")), "must be float [N >= 1"),
    ("export-crops-range", lambda f: _export(f, "--crops", str(f / "bright_crops.npy")), "must lie in [0, 1]"),
    ("export-crops-empty", lambda f: _export(f, "--crops", str(f / "empty_crops.npy")), "must be float [N >= 1"),
    ("export-crops-objects", lambda f: _export(f, "--crops", str(f / "object_crops.npy")), "not a .npy array"),
    ("export-crops-text", lambda f: _export(f, "--crops", str(f / "not_npy.npy")), "not a .npy array"),
    ("export-crops-npz", lambda f: _export(f, "--crops", str(f / "arrays.npz")), ".npz archive"),
    ("export-crops-missing", lambda f: _export(f, "--crops", str(f / "none.npy")), "crops file not found"),
    ("export-crop-ids-float", lambda f: _export(f, "--crops", str(f / "good_crops.npy"), "--crop-obj-ids",
                                                str(f / "float_ids.npy")), "must be 4 integers"),
    ("export-ids-without-crops", lambda f: _export(f, "--crop-obj-ids", str(f / "float_ids.npy")), "give --crops"),
    ("evaluate-split-is-a-file", lambda f: ["evaluate", str(f / "keys.pt"), "--split", str(f / "keys.pt"),
                                            "--models-dir", str(f / "a_folder")], "is a file, not a folder"),
    ("evaluate-models-dir-is-a-file", lambda f: ["evaluate", str(f / "keys.pt"), "--split", str(f / "a_folder"),
                                                 "--models-dir", str(f / "keys.pt")], "is a file, not a folder"),
    ("render-out-is-a-file", lambda f: ["render", "--objects", "builtin", "--images", "1", "--out", str(f / "keys.pt")],
     "is a file"),
    ("render-objects-missing", lambda f: ["render", "--images", "1", "--out", str(f / "r"), "--objects",
                                          str(f / "none")], "no such models folder"),
    ("preview-count-zero", lambda f: ["preview", "--split", str(f), "--out", str(f / "p.png"), "--count", "0"],
     "--count must be at least 1"),
    ("preview-count-negative", lambda f: ["preview", "--split", str(f), "--out", str(f / "p.png"), "--count", "-1"],
     "--count must be at least 1"),
    ("preview-split-is-a-file", lambda f: ["preview", "--split", str(f / "keys.pt"), "--out", str(f / "p.png")],
     "is a file, not a folder"),
    ("train-negative-conv", lambda f: ["train", "--set", "network.conv_channels=[-8, 16, 16]"],
     "network.conv_channels widths must be at least 1"),
    ("train-zero-hidden", lambda f: ["train", "--set", "network.hidden=[0, 16, 16]"], "network.hidden widths"),
    ("train-zero-kernel", lambda f: ["train", "--set", "network.conv_kernel=0"], "network.conv_kernel must be"),
    ("train-config-missing", lambda f: ["train", "--config", str(f / "none.toml")], "config file not found"),
    ("train-unknown-key", lambda f: ["train", "--set", "train.speed=3"], "unknown config key"),
]


@pytest.mark.parametrize(("argv", "expect"), [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_popcode_train_refuses_in_one_line(argv, expect, files, monkeypatch):
    stderr = io.StringIO()
    monkeypatch.setattr("sys.stderr", stderr)
    code = main(argv(files))
    lines = error_lines(stderr.getvalue())
    assert code == 2 and len(lines) == 1 and expect.lower() in lines[0].lower(), stderr.getvalue()
    assert not list(files.glob("*.onnx")) and not list(files.glob(".*.tmp"))  # nothing half-written left behind
