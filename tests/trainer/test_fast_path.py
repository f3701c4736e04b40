"""The training step's fast path: chosen by the CPU's flags, compiled and eager agree, every fallback says why."""

from __future__ import annotations

import copy
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from onnx import numpy_helper
from tiny import tiny_config, tiny_data, tiny_representation

from popcode_trainer.export.onnx_export import export_checkpoint
from popcode_trainer.train import checkpoint, fast_path
from popcode_trainer.train.fast_path import COMPILE_MIN_STEPS, GuardedForward, StepPath, choose_path
from popcode_trainer.train.loop import network_config, train
from popcode_trainer.train.network import build_network
from popcode_trainer.train.run_files import LAST_CHECKPOINT

CPU = torch.device("cpu")
AVX2 = frozenset({"sse4_2", "avx2", "fma"})
AMX = AVX2 | {"avx512f", "avx512_vnni", "amx_tile", "amx_bf16", "avx512_bf16"}


@pytest.mark.parametrize("flags, precision, expected", [
    (AVX2, "auto", "fp32"), (AMX, "auto", "bf16"), (AVX2 | {"avx512_bf16"}, "auto", "bf16"),
    (AMX, "fp32", "fp32"), (AVX2, "bf16", "bf16"),
])
def test_bf16_only_where_the_flags_allow_or_asked_for(flags, precision, expected):
    path = choose_path(precision, "off", CPU, 10, flags)
    assert path.precision == expected and path.channels_last and not path.compiled


def test_channels_last_only_for_widths_where_its_backward_runs():
    """torch 2.13's CPU backward in channels_last hung or aborted with 4 or 6 channels in the residual trunk."""
    assert choose_path("auto", "off", CPU, 10, AVX2, conv_widths=(16, 32, 64)).channels_last
    narrow = choose_path("auto", "off", CPU, 10, AVX2, conv_widths=(4, 8, 16))
    assert not narrow.channels_last and "NCHW" in narrow.reason and "NCHW" in narrow.describe()


def test_compile_auto_only_where_it_pays():
    assert not choose_path("auto", "auto", CPU, 10 * COMPILE_MIN_STEPS, AVX2).compiled  # measured slower there
    assert not choose_path("auto", "auto", CPU, COMPILE_MIN_STEPS - 1, AMX).compiled  # too short to win it back
    assert choose_path("auto", "auto", CPU, COMPILE_MIN_STEPS, AMX).compiled
    assert choose_path("auto", "on", CPU, 1, AVX2).compiled
    assert not choose_path("auto", "off", CPU, 1 << 30, AMX).compiled
    assert choose_path("auto", "auto", torch.device("cuda"), 1 << 30, AMX).precision == "fp32"  # CUDA: train.amp
    assert not choose_path("auto", "auto", torch.device("cuda"), 1 << 30, AMX).compiled  # not measured to pay yet
    assert "CUDA graphs" in choose_path("auto", "on", torch.device("cuda"), 1, AVX2).describe()


def tiny_model_and_batch(device: torch.device = CPU) -> tuple[torch.nn.Module, torch.Tensor]:
    config = tiny_config(Path("unused"))
    torch.manual_seed(0)
    model = build_network(network_config(config, tiny_representation(config))).to(device)
    images = torch.rand(4, 1, config.data.crop_size, config.data.crop_size, device=device)
    return model.to(memory_format=torch.channels_last), images.contiguous(memory_format=torch.channels_last)


# On CUDA the compiled step replays CUDA graphs (inductor may still skip them; bench/cuda_step.py shows the speed);
# only a machine with a GPU runs that case (a lent one: README).
DEVICES = [CPU, pytest.param(torch.device("cuda"), marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                              reason="needs a CUDA device"))]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.slow
def test_compiled_and_eager_steps_give_the_same_loss(device):
    model, images = tiny_model_and_batch(device)
    path = StepPath(channels_last=True, precision="fp32", compiled=True, reason="test")
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="training eager")  # a fallback would compare eager with eager
        compiled = GuardedForward(model, path)
        outputs = [compiled(images).detach().clone() for _ in range(3)]  # on CUDA: recorded, then replayed
    assert compiled.path.compiled and compiled.compiled is not None and compiled.compile_s > 0
    assert compiled.cuda_graphs == (device.type == "cuda")
    eager = model(images)
    for output in outputs:  # TF32 convolutions on a GPU round at about 1e-3
        torch.testing.assert_close(output, eager, rtol=1e-3 if device.type == "cuda" else 1e-4, atol=1e-4)
    compiled(images).square().mean().backward()  # the compiled backward runs too
    assert all(weight.grad is not None for weight in model.parameters() if weight.requires_grad)


def test_a_missing_compiler_falls_back_to_eager_with_one_line(monkeypatch):
    monkeypatch.setattr(fast_path, "compiler_missing", lambda: "no C++ compiler (c++, g++, clang++) on PATH")
    model, images = tiny_model_and_batch()
    with pytest.warns(UserWarning, match="training eager instead of compiled: no C\\+\\+ compiler") as caught:
        forward = GuardedForward(model, StepPath(True, "fp32", True, "test"))
    assert len(caught) == 1 and not forward.path.compiled and "fell back to eager" in forward.path.reason
    torch.testing.assert_close(forward(images), model(images), rtol=0, atol=0)
    assert forward.compile_s == 0.0


def test_a_failing_compile_falls_back_on_the_first_batch(monkeypatch):
    def broken_compile(module):
        def run(images):
            raise RuntimeError("InductorError: C++ compile error\nmany lines of compiler output")
        return run

    monkeypatch.setattr(torch, "compile", broken_compile)
    model, images = tiny_model_and_batch()
    forward = GuardedForward(model, StepPath(True, "fp32", True, "test"))
    with pytest.warns(UserWarning, match=r"the compile failed \(InductorError: C\+\+ compile error\)$"):
        output = forward(images)
    torch.testing.assert_close(output, model(images), rtol=0, atol=0)
    assert not forward.path.compiled
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="training eager")
        forward(images)  # said once, not every step


def test_bf16_training_records_its_path_and_exports_fp32(tmp_path):
    config = tiny_config(tmp_path / "run", epochs=1, precision="bf16", compile="off")
    rep = tiny_representation(config)
    train_set, val_set = tiny_data(rep)
    history = train(config, rep, train_set, val_set)
    assert np.isfinite(history[0].train_loss)
    state = checkpoint.load(tmp_path / "run" / LAST_CHECKPOINT)
    assert state["step_path"]["precision"] == "bf16" and state["step_path"]["channels_last"]
    assert state["config"]["train"]["precision"] == "bf16"
    crops = np.stack([val_set[i]["image"].numpy() for i in range(4)])
    export_checkpoint(tmp_path / "run" / LAST_CHECKPOINT, tmp_path / "m.onnx", crops)
    weights = [numpy_helper.to_array(t) for t in onnx.load(str(tmp_path / "m.onnx")).graph.initializer]
    assert all(w.dtype != np.float16 and w.dtype.name != "bfloat16" for w in weights)
    assert any(w.dtype == np.float32 for w in weights)


def test_a_run_from_before_these_settings_resumes(tmp_path):
    """A checkpoint whose config has no train.precision / train.compile resumes (they read as the defaults)."""
    config = tiny_config(tmp_path / "run", epochs=1)
    rep = tiny_representation(config)
    train_set, val_set = tiny_data(rep)
    train(config, rep, train_set, val_set)
    state = checkpoint.load(tmp_path / "run" / LAST_CHECKPOINT)
    for key in ("precision", "compile"):
        del state["config"]["train"][key]
    checkpoint.save_atomic(state, tmp_path / "run" / LAST_CHECKPOINT)
    history = train(replace(config, train=replace(config.train, epochs=2)), rep, train_set, val_set, resume=True)
    assert [row.epoch for row in history] == [2]


def test_a_compile_that_hangs_falls_back_at_the_deadline(monkeypatch):
    def hanging_compile(module):
        def run(images):
            time.sleep(120)  # a compile that never ends; without the deadline the call returns None after it
        return run

    monkeypatch.setattr(torch, "compile", hanging_compile)
    monkeypatch.setattr(fast_path, "COMPILE_DEADLINE_S", 0.2)
    model, images = tiny_model_and_batch()
    forward = GuardedForward(model, StepPath(True, "fp32", True, "test"))
    with pytest.warns(UserWarning, match=r"training eager instead of compiled: the compile took longer than 0.2 s$"):
        output = forward(images)
    torch.testing.assert_close(output, model(images), rtol=0, atol=0)
    assert not forward.path.compiled and "took longer" in forward.path.reason


def test_the_compile_warm_up_leaves_weights_gradients_and_statistics_as_one_step_would(monkeypatch):
    """Each new batch shape runs once, forward and backward, before its step: the batch-norm statistics then move
    once, as in an eager step, and no gradient is left behind; a shape seen before runs once."""
    calls = []

    def counting_compile(module):
        def run(images):
            calls.append(tuple(images.shape))
            return module(images)
        return run

    monkeypatch.setattr(torch, "compile", counting_compile)
    model, images = tiny_model_and_batch()
    eager = copy.deepcopy(model)
    forward = GuardedForward(model, StepPath(True, "fp32", True, "test"))
    torch.testing.assert_close(forward(images), eager(images), rtol=0, atol=0)
    for ours, theirs in zip(model.buffers(), eager.buffers(), strict=True):
        torch.testing.assert_close(ours, theirs, rtol=0, atol=0)
    assert all(weight.grad is None for weight in model.parameters())
    forward(images)
    forward(images[:2])
    assert calls == [(4, 1, 128, 128)] * 3 + [(2, 1, 128, 128)] * 2
