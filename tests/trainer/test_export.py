"""Export: the ONNX model meets the contract, matches torch, and the runtime decodes it like torch."""

from __future__ import annotations

import dataclasses
import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from calls import calls_of
from symmetry_cases import CASES
from synthetic import K, RotatedPoints, draw
from tiny import tiny_config, tiny_data, tiny_representation
from trained import pasted_frame, trained_checkpoint

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, random_rotations
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.model.decoding import decode_output
from popcode_runtime.model.engine import OnnxEngine
from popcode_runtime.model.metadata import ModelMetadata, Representation, RotationFrame
from popcode_trainer.cli import main
from popcode_trainer.data import hull
from popcode_trainer.data.bop import model_path
from popcode_trainer.data.meshes import load_mesh
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from popcode_trainer.export import onnx_export as export
from popcode_trainer.export.agreement import compare
from popcode_trainer.export.model_io import load_checkpoint_model, load_trained_model, read_onnx_metadata
from popcode_trainer.export.onnx_export import export_checkpoint, export_onnx
from popcode_trainer.export.quantise import NBITS_INT8_COMPUTE, quantise, quantised_path
from popcode_trainer.train import training_data
from popcode_trainer.train.config import Config
from popcode_trainer.train.loop import network_config, train
from popcode_trainer.train.network import NetworkConfig, PopcodeNet, build_network
from popcode_trainer.train.run_files import LAST_CHECKPOINT
from popcode_trainer.train.training_data import build_training_data

RENDERED_OBJ_ID = 6  # a part without symmetry: its code needs no narrower sigma


def test_a_model_trained_on_other_crops_exports_with_their_size(tmp_path: Path) -> None:
    """data.crop_size travels into the metadata: export checks parity on such crops, the runtime crops at that size."""
    config = tiny_config(tmp_path / "run", epochs=1)
    config = dataclasses.replace(config, data=dataclasses.replace(config.data, crop_size=48))
    rep = tiny_representation(config)
    train_set, val_set = RotatedPoints(32, rep.target, seed=1, size=48), RotatedPoints(8, rep.target, seed=2, size=48)
    train(config, rep, train_set, val_set, val_instances=val_set.instances)
    crops = np.stack([val_set[i]["image"].numpy() for i in range(len(val_set))])
    parity, = export_checkpoint(tmp_path / "run" / LAST_CHECKPOINT, tmp_path / "m.onnx", crops)
    assert parity.max_abs_diff < 1e-4
    estimator = PoseEstimator(tmp_path / "m.onnx")
    assert estimator.metadata.input_size == 48
    assert estimator.crops(np.zeros((100, 120), np.float32), [(10, 10, 40, 30)]).shape == (1, 1, 48, 48)
    assert len(estimator.predict(np.zeros((100, 120), np.float32), [(10, 10, 40, 30)])) == 1


def test_a_run_without_validation_exports_a_model_the_runtime_reads(tmp_path: Path) -> None:
    """No validation split: the best error is inf, which JSON (so the runtime) cannot hold; exported as null."""
    config = tiny_config(tmp_path / "run", epochs=1)
    rep = tiny_representation(config)
    train_set, val_set = tiny_data(rep)
    train(config, rep, train_set, None)
    crops = np.stack([val_set[i]["image"].numpy() for i in range(4)])
    export_checkpoint(tmp_path / "run" / LAST_CHECKPOINT, tmp_path / "m.onnx", crops)
    assert PoseEstimator(tmp_path / "m.onnx").metadata.training["best_val_error_deg"] is None


def test_metadata_read_from_the_file_is_the_runtimes(tmp_path: Path) -> None:
    """Reports read what a model is without an inference session; it is what the runtime reads."""
    config = tiny_config(tmp_path / "run", epochs=1)
    rep = tiny_representation(config)
    train_set, val_set = tiny_data(rep)
    train(config, rep, train_set, val_set)
    export_checkpoint(tmp_path / "run" / LAST_CHECKPOINT, tmp_path / "m.onnx", np.stack([draw(np.eye(3))[None]]))
    assert read_onnx_metadata(tmp_path / "m.onnx").to_props() == PoseEstimator(tmp_path / "m.onnx").metadata.to_props()
    (tmp_path / "broken.onnx").write_bytes(b"not a model")
    with pytest.raises(PopcodeError, match="broken.onnx: not a readable ONNX model"):
        read_onnx_metadata(tmp_path / "broken.onnx")


def optimised_op_types(path: Path, out: Path) -> list[str]:
    """Op types of the graph onnxruntime's CPU provider runs after its optimisations."""
    options = ort.SessionOptions()
    options.optimized_model_filepath = str(out)
    ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    return [node.op_type for node in onnx.load(str(out)).graph.node]


@pytest.mark.parametrize("name", Representation.values())
def test_runtime_gives_the_torch_rotations(tmp_path: Path, name: str) -> None:
    ckpt, _ = trained_checkpoint(tmp_path, representation=name, rotation_frame=RotationFrame.ALLOCENTRIC)
    frame, boxes = pasted_frame()
    onnx_path = tmp_path / "model.onnx"
    export_checkpoint(ckpt, onnx_path, np.stack([draw(np.eye(3))[None]]))

    estimator = PoseEstimator(onnx_path)
    predictions = estimator.predict(frame, boxes, K=K)

    model, metadata = load_checkpoint_model(ckpt)
    rep = tiny_representation(tiny_config(tmp_path, representation=name,
                                          rotation_frame=RotationFrame.ALLOCENTRIC))
    with torch.no_grad():
        output = model(torch.from_numpy(estimator.crops(frame, boxes))).numpy()
    R_frame = rep.decode(output).R
    for prediction, R, box in zip(predictions, R_frame, boxes, strict=True):
        centre = (box[0] + box[2] / 2, box[1] + box[3] / 2)
        expected = rep.frame_rotation(np.eye(3), K, box).T @ R  # R_ray R_allo
        assert np.allclose(prediction.R_m2c, expected, atol=1e-4), centre
    assert metadata.training["epochs"] == 1



def test_cross_entropy_model_exports_its_code(tmp_path: Path) -> None:
    """Trained on logits, exported as softmax * code mass: the runtime reads a code, argmax unchanged."""
    ckpt, crops = trained_checkpoint(tmp_path, loss="cross_entropy")
    onnx_path = tmp_path / "model.onnx"
    export_checkpoint(ckpt, onnx_path, crops)
    code = OnnxEngine(onnx_path)(crops)
    state = torch.load(ckpt, weights_only=True)
    rep = tiny_representation(tiny_config(tmp_path, loss="cross_entropy"))
    logits_model = build_network(network_config(tiny_config(tmp_path, loss="cross_entropy"), rep))
    logits_model.load_state_dict(state["model"])
    with torch.no_grad():
        logits = logits_model.eval()(torch.from_numpy(crops)).numpy()
    mass = float(PopulationCode(rep.layout).encode(np.eye(3)).sum())
    np.testing.assert_allclose(code.sum(axis=1), mass, rtol=1e-4)
    np.testing.assert_array_equal(code.argmax(axis=1), logits.argmax(axis=1))
    metadata = PoseEstimator(onnx_path).metadata
    np.testing.assert_allclose(decode_output(code, metadata).R, rep.decode(logits).R, atol=1e-6)

def test_export_that_fails_its_parity_check_leaves_no_model(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt, crops = trained_checkpoint(tmp_path)
    onnx_path = tmp_path / "model.onnx"

    class ShiftedTorch(export.TorchEngine):  # torch's outputs with the argmax moved: a wrong export
        def __call__(self, batch: np.ndarray) -> np.ndarray:
            return np.roll(super().__call__(batch), 1, axis=1)

    monkeypatch.setattr(export, "TorchEngine", ShiftedTorch)
    with pytest.raises(PopcodeError, match="disagree on the argmax"):
        export_checkpoint(ckpt, onnx_path, crops)
    assert not onnx_path.exists() and list(tmp_path.glob("*.onnx")) == []


def _nbits_accuracy_levels(path: Path) -> list[int | None]:
    """The ``accuracy_level`` of each ``MatMulNBits`` node of an ONNX file (None where it is unset)."""
    return [next((onnx.helper.get_attribute_value(attr) for attr in node.attribute if attr.name == "accuracy_level"),
                 None) for node in onnx.load(str(path)).graph.node if node.op_type == "MatMulNBits"]


def test_export_meets_the_contract_and_quantises(tmp_path: Path) -> None:
    ckpt, crops = trained_checkpoint(tmp_path)
    onnx_path = tmp_path / "out" / "model.onnx"
    results = export_checkpoint(ckpt, onnx_path, crops, quantisations=("int8", "nbits4", "nbits8"),
                                split_output=100)
    parity, *quantised = results
    assert parity.max_abs_diff < 1e-4 and parity.argmax_agreement == parity.pose_agreement == 1.0
    assert [r.path.name for r in quantised] == ["model.int8.onnx", "model.nbits4.onnx", "model.nbits8.onnx"]
    assert all(0.0 <= r.argmax_agreement <= r.pose_agreement <= 1.0 for r in quantised)  # same argmax: same pose

    model = onnx.load(str(onnx_path))
    ops = {node.op_type for node in model.graph.node}
    assert "MatMul" in ops and "Concat" in ops
    assert [i.name for i in model.graph.input] == ["image"] and [o.name for o in model.graph.output] == ["code"]
    batch_dim = model.graph.input[0].type.tensor_type.shape.dim[0]
    assert batch_dim.dim_param and not batch_dim.dim_value
    for r in quantised:
        quantised_model = onnx.load(str(r.path))
        assert {p.key: p.value for p in quantised_model.metadata_props} == \
            {p.key: p.value for p in model.metadata_props}
    for nbits in quantised[1:]:  # every MatMulNBits computes on int8 activations (the default level is slower)
        assert set(_nbits_accuracy_levels(nbits.path)) == {NBITS_INT8_COMPUTE}, nbits.path.name
    assert quantised[0].argmax_agreement >= 0.99  # calibrated on these crops
    head = [init for init in model.graph.initializer if init.name.startswith("head.")]
    assert len(head) == 12 and max(max(init.dims) for init in head) <= 100  # 504 outputs in blocks of 100
    PoseEstimator(quantised[1].path)  # the runtime accepts a quantised model


def test_int8_is_static_on_every_conv_and_matmul(tmp_path: Path) -> None:
    """No ConvInteger (dynamic, slow on CPU): every Conv/Gemm/MatMul reads int8 weights and int8 activations.

    Untrained, as in bench/latency.py: equal (zero) folded BatchNorm biases
    reach the graph through Identity, which must not keep a conv in float.
    """
    config = NetworkConfig(output_dim=42 * 12, conv_channels=(8, 8, 8), squeeze_channels=4, hidden=(32, 32, 32))
    torch.manual_seed(0)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE,
                             code=CodeLayout(n_axes=42, n_angles=12, sigma_deg=30.0), objects={1: {"diameter": 100.0}})
    float_path = export_onnx(PopcodeNet(config).eval(), metadata, tmp_path / "model.onnx")
    assert "Identity" in {node.op_type for node in onnx.load(str(float_path)).graph.node}
    crops = np.stack([draw(np.linalg.qr(np.random.default_rng(i).normal(size=(3, 3)))[0])[None] for i in range(8)])
    int8_path = quantise(float_path, "int8", metadata, calibration=crops)
    graph = onnx.load(str(int8_path)).graph
    assert not {"ConvInteger", "MatMulInteger", "DynamicQuantizeLinear"} & {node.op_type for node in graph.node}
    dequantised = {node.output[0] for node in graph.node if node.op_type == "DequantizeLinear"}
    heavy = [node for node in graph.node if node.op_type in ("Conv", "Gemm", "MatMul")]
    assert len(heavy) == 4 + 3 + 1 and all(set(node.input[:2]) <= dequantised for node in heavy)
    # What onnxruntime runs: every QDQ group fused into an integer kernel, no float conv or matmul left.
    running = optimised_op_types(int8_path, tmp_path / "optimised.onnx")
    assert running.count("QLinearConv") == 4 and not {"Conv", "Gemm", "MatMul", "FusedConv"} & set(running)
    assert all(node.op_type != "QuantizeLinear" for node in graph.node if "image" in node.input)  # float normalisation
    agreement = compare(int8_path, OnnxEngine(int8_path)(crops), OnnxEngine(float_path)(crops), metadata)
    assert agreement.argmax_agreement == agreement.pose_agreement == 1.0  # calibrated on these crops
    with pytest.raises(PopcodeError, match="calibration crops"):
        quantise(float_path, "int8", metadata)



def test_export_crops_come_from_every_object(tmp_path: Path) -> None:
    """The parity and int8 calibration crops are spread over the held-out instances, which come ordered by
    object: a model of two parts is calibrated on both, not on the first one's crops alone."""
    split = render_builtin_split(tmp_path / "split", 3, obj_ids=[3, 6], random_position=True)
    config = Config.from_dict({"data": {"splits": [str(split)], "models_dir": str(split / BUILTIN_MODELS_FOLDER),
                                        "num_workers": 0, "val_fraction": 0.0}})
    split_read = training_data.read_training_split(config)
    assert [inst.obj_id for inst in split_read.instances] == [3, 3, 3, 6, 6, 6]
    crops, obj_ids = training_data.validation_crops(config, count=2, split=split_read)
    assert crops.shape == (2, 1, config.data.crop_size, config.data.crop_size) and obj_ids.tolist() == [3, 6]
    assert training_data.validation_crops(config, count=100, split=split_read)[1].tolist() == [3, 3, 3, 6, 6, 6]


def test_fp16_halves_the_file_and_runs_in_float(tmp_path: Path) -> None:
    """fp16 stores every weight in half precision: the file halves, onnxruntime folds the casts away (the graph it
    runs computes in float32, as the float model's), the outputs stay within half precision's rounding and the
    metadata travels; a weight beyond float16's range is refused, not turned into inf."""
    config = NetworkConfig(output_dim=42 * 12, conv_channels=(8, 8, 8), squeeze_channels=4, hidden=(32, 32, 32))
    torch.manual_seed(0)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE,
                             code=CodeLayout(n_axes=42, n_angles=12, sigma_deg=30.0), objects={1: {"diameter": 100.0}})
    float_path = export_onnx(PopcodeNet(config).eval(), metadata, tmp_path / "model.onnx")
    half_path = quantise(float_path, "fp16", metadata)
    assert half_path.name == "model.fp16.onnx"
    assert half_path.stat().st_size < 0.6 * float_path.stat().st_size
    stored = onnx.load(str(half_path)).graph
    assert {init.data_type for init in stored.initializer} <= {onnx.TensorProto.FLOAT16, onnx.TensorProto.INT64}
    assert "Cast" not in optimised_op_types(half_path, tmp_path / "optimised.onnx")
    crops = np.stack([draw(np.linalg.qr(np.random.default_rng(i).normal(size=(3, 3)))[0])[None] for i in range(8)])
    half, full = OnnxEngine(half_path)(crops), OnnxEngine(float_path)(crops)
    assert half.dtype == np.float32
    np.testing.assert_allclose(half, full, atol=5e-3 * np.abs(full).max())
    assert read_onnx_metadata(half_path) == read_onnx_metadata(float_path)
    huge = onnx.load(str(float_path))
    first = next(init for init in huge.graph.initializer if init.data_type == onnx.TensorProto.FLOAT)
    first.CopyFrom(onnx.numpy_helper.from_array(np.full(onnx.numpy_helper.to_array(first).shape, 1e6, np.float32),
                                                first.name))
    onnx.save(huge, str(tmp_path / "huge.onnx"))
    with pytest.raises(PopcodeError, match="beyond float16"):
        quantise(tmp_path / "huge.onnx", "fp16", metadata)
    assert not (tmp_path / "huge.fp16.onnx").exists()


def test_nbits8_fp16_is_the_smallest_near_float_copy(tmp_path: Path) -> None:
    """nbits8-fp16: the output layer's MatMul in 8-bit blocks, every other weight in half precision: smaller than
    either alone, run by onnxruntime (its casts folded away), outputs near float's, metadata kept."""
    config = NetworkConfig(output_dim=162 * 12, conv_channels=(8, 8, 8), squeeze_channels=4, hidden=(32, 32, 64))
    torch.manual_seed(0)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE,
                             code=CodeLayout(n_axes=162, n_angles=12, sigma_deg=30.0), objects={1: {"diameter": 100.0}})
    float_path = export_onnx(PopcodeNet(config).eval(), metadata, tmp_path / "model.onnx")
    sizes = {kind: quantise(float_path, kind, metadata).stat().st_size for kind in ("fp16", "nbits8", "nbits8-fp16")}
    assert sizes["nbits8-fp16"] < min(sizes["fp16"], sizes["nbits8"])
    both = quantised_path(float_path, "nbits8-fp16")
    stored = onnx.load(str(both)).graph
    assert set(_nbits_accuracy_levels(both)) == {NBITS_INT8_COMPUTE}
    assert onnx.TensorProto.FLOAT not in {init.data_type for init in stored.initializer}
    assert "Cast" not in optimised_op_types(both, tmp_path / "optimised.onnx")
    crops = np.stack([draw(np.linalg.qr(np.random.default_rng(i).normal(size=(3, 3)))[0])[None] for i in range(8)])
    small, full = OnnxEngine(both)(crops), OnnxEngine(float_path)(crops)
    np.testing.assert_allclose(small, full, atol=2e-2 * np.abs(full).max())
    assert read_onnx_metadata(both) == read_onnx_metadata(float_path)
    PoseEstimator(both)  # the runtime accepts it


def test_int8_nbits8_runs_the_trunk_in_int8_and_the_output_layer_in_8_bit_blocks(tmp_path: Path) -> None:
    """int8-nbits8: every conv and hidden layer fused into an integer kernel, the output layer's MatMul as 8-bit
    blocks on int8 activations; it agrees with float on the crops it was calibrated on and keeps the metadata."""
    config = NetworkConfig(output_dim=42 * 12, conv_channels=(8, 8, 8), squeeze_channels=4, hidden=(32, 32, 32))
    torch.manual_seed(0)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE,
                             code=CodeLayout(n_axes=42, n_angles=12, sigma_deg=30.0), objects={1: {"diameter": 100.0}})
    float_path = export_onnx(PopcodeNet(config).eval(), metadata, tmp_path / "model.onnx")
    crops = np.stack([draw(np.linalg.qr(np.random.default_rng(i).normal(size=(3, 3)))[0])[None] for i in range(8)])
    mixed = quantise(float_path, "int8-nbits8", metadata, calibration=crops)
    assert mixed == quantised_path(float_path, "int8-nbits8")
    assert _nbits_accuracy_levels(mixed) == [NBITS_INT8_COMPUTE]
    running = optimised_op_types(mixed, tmp_path / "optimised.onnx")
    assert running.count("QLinearConv") == 4 and running.count("MatMulNBits") == 1
    assert not {"Conv", "FusedConv", "ConvInteger", "MatMul", "FusedGemm", "Gemm"} & set(running)
    agreement = compare(mixed, OnnxEngine(mixed)(crops), OnnxEngine(float_path)(crops), metadata)
    assert agreement.argmax_agreement == agreement.pose_agreement == 1.0
    assert read_onnx_metadata(mixed) == read_onnx_metadata(float_path)
    with pytest.raises(PopcodeError, match="int8-nbits8 quantisation needs calibration crops"):
        quantise(float_path, "int8-nbits8", metadata)


def test_residual_trunk_exports_and_quantises_statically(tmp_path: Path) -> None:
    """The residual trunk's graph: onnxruntime matches torch, and int8 runs every conv as QLinearConv."""
    config = NetworkConfig(output_dim=42 * 12, conv_channels=(8, 8, 16), squeeze_channels=4, hidden=(32, 32, 32),
                           trunk="residual")
    torch.manual_seed(0)
    model = PopcodeNet(config).eval()
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE,
                             code=CodeLayout(n_axes=42, n_angles=12, sigma_deg=30.0), objects={1: {"diameter": 100.0}})
    float_path = export_onnx(model, metadata, tmp_path / "model.onnx")
    crops = np.stack([draw(np.linalg.qr(np.random.default_rng(i).normal(size=(3, 3)))[0])[None] for i in range(8)])
    with torch.no_grad():
        expected = model(torch.from_numpy(crops)).numpy()
    np.testing.assert_allclose(OnnxEngine(float_path)(crops), expected, atol=1e-4)
    int8_path = quantise(float_path, "int8", metadata, calibration=crops)
    running = optimised_op_types(int8_path, tmp_path / "optimised.onnx")
    convs = 1 + 3 * 3 + 1  # stem, two body convs and a shortcut per block, squeeze
    assert running.count("QLinearConv") == convs and not {"Conv", "FusedConv", "ConvInteger"} & set(running)

GRID = CodeLayout(n_axes=642, n_angles=36, sigma_deg=20.0)
AXIS_GRID = CodeLayout(n_axes=642, axis_only=True, symmetry_axis=(0.0, 0.0, 1.0))
HALF_TURN_X = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.pi)


def turn_z(angle_deg: float) -> np.ndarray:
    return axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.deg2rad(angle_deg))


def two_peak_outputs(layout: CodeLayout, turn: np.ndarray, count: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Codes with near-equal peaks at R and R @ turn: the reference's peak at R is 5 % higher, the output's at
    R @ turn, as when quantisation noise swaps which of two peaks wins."""
    pc = PopulationCode(layout)
    R = random_rotations(count, np.random.default_rng(7))
    both = pc.encode(R, np.stack([np.eye(3), turn]))
    return both + 0.05 * pc.encode(R @ turn), both + 0.05 * pc.encode(R)


@pytest.mark.parametrize(("layout", "case", "turn", "pose_agreement"), [
    (GRID, "two_fold", turn_z(180), 1.0),  # the two peaks are one pose of this object
    (GRID, "four_fold", turn_z(90), 1.0),
    (GRID, "two_fold", turn_z(90), 0.0),  # a quarter turn is another pose of a 2-fold object
    (GRID, "none", turn_z(180), 0.0),
    (AXIS_GRID, "continuous_flip", HALF_TURN_X, 1.0),  # the axis flipped end to end: the same pose
    (AXIS_GRID, "continuous", HALF_TURN_X, 0.0),
])
def test_pose_agreement_counts_swapped_symmetric_peaks_as_agreeing(layout: CodeLayout, case: str,
                                                                   turn: np.ndarray, pose_agreement: float) -> None:
    output, reference = two_peak_outputs(layout, turn)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE, code=layout, objects={3: CASES[case]})
    result = compare(Path("variant.onnx"), output, reference, metadata)
    assert result.argmax_agreement == 0.0
    assert result.pose_agreement == pose_agreement


def test_pose_agreement_takes_each_crops_symmetries_from_its_object() -> None:
    output, reference = two_peak_outputs(GRID, turn_z(180), count=12)
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE, code=GRID,
                             objects={1: CASES["none"], 2: CASES["two_fold"]})
    assert compare(Path("v.onnx"), output, reference, metadata, obj_ids=[2] * 12).pose_agreement == 1.0
    assert compare(Path("v.onnx"), output, reference, metadata, obj_ids=[1, 2] * 6).pose_agreement == 0.5
    assert compare(Path("v.onnx"), output, reference, metadata).pose_agreement is None  # objects unknown
    with pytest.raises(PopcodeError, match=r"object ids \[5\] are not in this model"):
        compare(Path("v.onnx"), output, reference, metadata, obj_ids=[5] * 12)
    with pytest.raises(PopcodeError, match="got 3 object ids for 12 crops"):
        compare(Path("v.onnx"), output, reference, metadata, obj_ids=[1, 2, 2])


@pytest.fixture(scope="module")
def rendered_split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return render_builtin_split(tmp_path_factory.mktemp("split"), 6, obj_ids=[RENDERED_OBJ_ID], random_position=True)


def rendered_checkpoint(split: Path, folder: Path) -> tuple[Path, Path]:
    """A tiny network trained one epoch on the rendered split with its own copy of the models folder (so that a
    test may delete it): the checkpoint and that folder."""
    models = Path(shutil.copytree(split / BUILTIN_MODELS_FOLDER, folder / "models"))
    config = Config.from_dict({
        "data": {"splits": [str(split)], "models_dir": str(models), "num_workers": 0, "val_fraction": 0.5},
        "code": {"n_axes": 42, "n_angles": 12, "sigma_deg": 30.0},
        "network": {"conv_channels": [4, 4, 4], "squeeze_channels": 2, "hidden": [16, 16, 16]},
        "train": {"epochs": 1, "batch_size": 2, "out_dir": str(folder / "run"), "device": "cpu"},
    })
    data = build_training_data(config, progress=False)
    train(config, data.representation, data.train_set, data.val_set, val_instances=data.val_instances)
    return folder / "run" / LAST_CHECKPOINT, models


def mesh_hull_points(models: Path) -> list[list[float]]:
    return hull.hull_points_mm(np.asarray(load_mesh(model_path(models, RENDERED_OBJ_ID)).vertices)).tolist()


@pytest.mark.slow
def test_export_and_evaluate_commands_read_the_checkpoint_once(rendered_split: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The default export (validation crops, confidence fit, parity, int8) and an evaluation of the .pt read the
    file once each; the hull points stored at training are not computed again; the export reads the training
    split once for its crops and the calibration."""
    ckpt, models = rendered_checkpoint(rendered_split, tmp_path)
    loads, hulls = calls_of(monkeypatch, torch, "load"), calls_of(monkeypatch, hull, "hull_points_mm")
    splits = calls_of(monkeypatch, training_data, "read_bop_split")
    assert main(["export", str(ckpt), "--out", str(tmp_path / "model.onnx"), "--quantize", "int8"]) == 0
    assert [args[0] for args in loads] == [ckpt] and hulls == []
    assert [Path(args[0]) for args in splits] == [rendered_split]
    loads.clear()
    assert main(["evaluate", str(ckpt), "--split", str(rendered_split), "--models-dir", str(models),
                 "--out", str(tmp_path / "eval"), "--no-vsd"]) == 0
    assert [args[0] for args in loads] == [ckpt] and hulls == []


@pytest.mark.slow
def test_export_needs_no_models_folder(rendered_split: Path, tmp_path: Path) -> None:
    """Training stored each object's hull points, computed from its mesh as export did: the models folder may go."""
    ckpt, models = rendered_checkpoint(rendered_split, tmp_path)
    expected = mesh_hull_points(models)
    shutil.rmtree(models)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="no mesh")
        export_checkpoint(ckpt, tmp_path / "model.onnx", np.stack([draw(np.eye(3))[None]]))
    assert PoseEstimator(tmp_path / "model.onnx").metadata.objects[RENDERED_OBJ_ID]["hull_points_mm"] == expected


@pytest.mark.slow
def test_a_checkpoint_without_hull_points_gets_them_from_its_meshes(rendered_split: Path, tmp_path: Path) -> None:
    """A checkpoint written before hull points were stored: they come from the models folder, as they did; without
    it the object keeps its box corners, with a warning."""
    ckpt, models = rendered_checkpoint(rendered_split, tmp_path)
    state = torch.load(ckpt, weights_only=True)
    objects = json.loads(state["metadata"]["popcode.objects"])
    assert objects[str(RENDERED_OBJ_ID)]["hull_points_mm"] == mesh_hull_points(models)
    for info in objects.values():
        del info["hull_points_mm"]
    state["metadata"]["popcode.objects"] = json.dumps(objects)
    torch.save(state, tmp_path / "old.pt")
    assert load_trained_model(tmp_path / "old.pt").metadata.objects[RENDERED_OBJ_ID]["hull_points_mm"] == \
        mesh_hull_points(models)
    shutil.rmtree(models)
    with pytest.warns(UserWarning, match=rf"no mesh .* for objects \[{RENDERED_OBJ_ID}\]"):
        assert "hull_points_mm" not in load_trained_model(tmp_path / "old.pt").metadata.objects[RENDERED_OBJ_ID]
