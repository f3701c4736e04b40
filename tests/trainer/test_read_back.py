"""An exported model read back into the trainer's network (export.read_back): the float file's outputs exactly, the
quantised copies' near enough, BatchNorms that compute the same in training mode, the output layer's column blocks
in order; a start carrying the output layer fine-tunes only a run of the same code; bad files named in one line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from tiny import tiny_config, tiny_data, tiny_representation

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.model.engine import OnnxEngine
from popcode_trainer.export.model_io import TrainedModel, load_trained_model
from popcode_trainer.export.onnx_export import export_trained
from popcode_trainer.export.quantise import quantise
from popcode_trainer.export.read_back import read_back
from popcode_trainer.train.loop import train
from popcode_trainer.train.network import build_network
from popcode_trainer.train.pretrained import (
    OUTPUT_MODULE,
    POSE_START,
    TRANSFERRED_MODULES,
    apply_start,
    carries_output_layer,
    describe,
    network_shape,
    read_start,
    save_start,
)
from popcode_trainer.train.run_files import LAST_CHECKPOINT


@dataclasses.dataclass(frozen=True)
class Exported:
    path: Path
    trained: TrainedModel
    crops: np.ndarray  # held out
    val_loss: float  # of the exported (last) epoch


@pytest.fixture(scope="module", params=["paper", "residual"])
def exported(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Exported:
    """A tiny model of each trunk trained two epochs, exported with its output layer in three column blocks."""
    folder = tmp_path_factory.mktemp(request.param)
    config = tiny_config(folder / "run", epochs=2)
    config = dataclasses.replace(config, network=dataclasses.replace(config.network, trunk=request.param))
    representation = tiny_representation(config)
    train_set, val_set = tiny_data(representation, train_count=96, val_count=48)
    epochs = train(config, representation, train_set, val_set, val_instances=val_set.instances)
    crops = np.stack([val_set[i]["image"].numpy() for i in range(len(val_set))])
    trained = load_trained_model(folder / "run" / LAST_CHECKPOINT)
    path = folder / "model.onnx"
    export_trained(trained, path, crops, split_output=200)  # 504 outputs: blocks of 200, 200 and 104
    return Exported(path, trained, crops, epochs[-1].val_loss)


def test_the_float_file_is_read_back_to_its_outputs(exported: Exported) -> None:
    path, trained, crops = exported.path, exported.trained, exported.crops
    assert sum(node.op_type == "MatMul" for node in onnx.load(str(path)).graph.node) == 3
    model, metadata = read_back(path, crops)
    assert metadata.objects == trained.metadata.objects
    assert model.config == trained.network.config
    with torch.no_grad():
        rebuilt = model(torch.from_numpy(crops)).numpy()
        reference = trained.network(torch.from_numpy(crops)).numpy()
    np.testing.assert_allclose(rebuilt, reference, atol=1e-4 * np.abs(reference).max())
    np.testing.assert_allclose(rebuilt, OnnxEngine(path)(crops), atol=1e-4 * np.abs(reference).max())


def test_the_batch_norms_compute_the_same_in_training_mode(exported: Exported) -> None:
    """A fine-tune's first batches see the file's network: BatchNorm from batch statistics equals the folded
    convolution on the crops it was fitted to."""
    path, crops = exported.path, exported.crops
    model, _ = read_back(path, crops)
    with torch.no_grad():
        evaluated = model.eval()(torch.from_numpy(crops)).numpy()
        training = model.train()(torch.from_numpy(crops)).numpy()
    np.testing.assert_allclose(training, evaluated, atol=1e-3 * np.abs(evaluated).max())


@pytest.mark.parametrize("kind, tolerance", [("fp16", 2e-2), ("nbits8-fp16", 5e-2), ("int8-nbits8", 0.2)])
def test_quantised_copies_are_read_back_near_the_float_model(exported: Exported,
                                                             kind: str, tolerance: float) -> None:
    path, trained, crops = exported.path, exported.trained, exported.crops
    copy = quantise(path, kind, trained.metadata, calibration=crops)
    model, _ = read_back(copy, crops)
    with torch.no_grad():
        rebuilt = model(torch.from_numpy(crops)).numpy()
        reference = trained.network(torch.from_numpy(crops)).numpy()
    scale = np.abs(reference).max()
    assert np.abs(rebuilt - reference).max() < tolerance * scale, kind


def test_a_start_with_the_output_layer_fills_a_run_of_the_same_code_only(
        exported: Exported, tmp_path: Path) -> None:
    path, crops = exported.path, exported.crops
    model, _ = read_back(path, crops)
    state = {name: tensor for name, tensor in model.state_dict().items()
             if name.split(".")[0] in (*TRANSFERRED_MODULES, OUTPUT_MODULE)}
    card = {"from_model": str(path), "epochs": 2, "commit": "abc1234"}
    start_path = save_start(POSE_START, network_shape(model.config), state, tmp_path / "start.pt", card)
    start = read_start(start_path)
    assert carries_output_layer(start)
    assert describe(start) == "the weights of model.onnx, 2 epochs, commit abc1234"
    torch.manual_seed(5)
    target = build_network(model.config)
    assert apply_start(target, start, model.config) == len(state)
    for name, tensor in model.state_dict().items():
        torch.testing.assert_close(target.state_dict()[name], tensor, msg=name)
    other_code = dataclasses.replace(model.config, output_dim=42 * 6)
    with pytest.raises(PopcodeError, match=r"its output layer \(head.bias \(504,\)\) do not fit this network's "
                                           r"\(\(252,\)\): a start with an output layer fits only a run of the same"):
        apply_start(build_network(other_code), start, other_code)


def test_a_run_fine_tunes_from_a_start_with_the_output_layer(exported: Exported,
                                                             tmp_path: Path) -> None:
    """train.init naming such a start: the run's first validation loss is the exported model's, not a random
    network's (one epoch at a tiny rate barely moves it)."""
    model, _ = read_back(exported.path, exported.crops)
    state = {name: tensor for name, tensor in model.state_dict().items()
             if name.split(".")[0] in (*TRANSFERRED_MODULES, OUTPUT_MODULE)}
    start_path = save_start(POSE_START, network_shape(model.config), state, tmp_path / "start.pt", {"parts": 1})
    losses = {}
    for init in (str(start_path), "none"):
        config = tiny_config(tmp_path / f"run-{init == 'none'}", epochs=1, init=init, lr=1e-6)
        config = dataclasses.replace(config, network=dataclasses.replace(config.network,
                                                                         trunk=model.config.trunk))
        representation = tiny_representation(config)
        train_set, val_set = tiny_data(representation, train_count=96, val_count=48)
        losses[init] = train(config, representation, train_set, val_set,
                             val_instances=val_set.instances)[-1].val_loss
    assert abs(losses[str(start_path)] - exported.val_loss) < 0.02 * exported.val_loss, losses
    assert losses["none"] > 1.1 * exported.val_loss, losses


def test_files_it_cannot_read_back_are_named(exported: Exported, tmp_path: Path) -> None:
    path, crops = exported.path, exported.crops
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(PopcodeError, match="garbage.onnx: not a readable ONNX model"):
        read_back(garbage, crops)
    stripped = onnx.load(str(path))
    for prop in stripped.metadata_props:
        if prop.key == "popcode.training":
            prop.value = "{}"
    onnx.save(stripped, str(tmp_path / "untrained.onnx"))
    with pytest.raises(PopcodeError, match="untrained.onnx: its metadata has no training config"):
        read_back(tmp_path / "untrained.onnx", crops)
