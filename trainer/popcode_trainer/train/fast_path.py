"""Which fast path a training step takes on this machine: memory layout, precision and a compiled step.

- ``channels_last``: where every convolution width is a multiple of
  :data:`CHANNELS_LAST_WIDTH_MULTIPLE`. The convolutions and batch norms then run
  in the layout oneDNN prefers, without the layout copies an NCHW step makes.
  With narrower odd widths (4 or 6 channels in the residual trunk) torch 2.13's
  CPU backward in ``channels_last`` hangs or corrupts memory, so those stay NCHW.
- ``train.precision``: ``"auto"`` trains in bf16 autocast on a CPU with native
  bf16 (``amx_bf16`` or ``avx512_bf16`` among its flags) and in fp32 elsewhere
  (emulated bf16 is slower than fp32); ``"fp32"`` / ``"bf16"`` force one. CUDA
  keeps its own mixed precision (``train.amp``). The exported model is fp32
  whatever the training precision.
- ``train.compile``: ``"auto"`` compiles the step (``torch.compile``) where it
  was measured to pay for its compile time: a CPU with native bf16 and a run of
  at least :data:`COMPILE_MIN_STEPS` steps; on an AVX2-only CPU the compiled
  step was no clear gain over the eager ``channels_last`` one (slower in three
  runs, faster in one; ``bench/results/training.md``). ``"on"`` / ``"off"``
  force it. A missing C++ compiler, a failing compile or one that runs past :data:`COMPILE_DEADLINE_S`
  (each new batch shape compiles its forward and backward once, under that
  bound) falls back to the eager step, saying why in one line. On a CUDA device
  ``"auto"`` stays eager (not yet measured to pay there); ``"on"`` compiles with
  CUDA graphs (:data:`CUDA_COMPILE_MODE`): the eager step of the small network is
  bound by launching its kernels, not by the GPU (``bench/results/cuda-step.md``).

Resuming a run is bit-exact on the fp32 eager path; bf16 and compiled steps may
round differently after a resume (another compile, another kernel choice).
"""

from __future__ import annotations

import shutil
import sys
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

from popcode_runtime.base.errors import first_line
from popcode_runtime.inference.benchmark import cpu_info

from .deadline import deadline

PRECISIONS = ("auto", "fp32", "bf16")
COMPILE_CHOICES = ("auto", "on", "off")
NATIVE_BF16_FLAGS = frozenset({"amx_bf16", "avx512_bf16"})
CHANNELS_LAST_WIDTH_MULTIPLE = 8  # widths 8, 16, 24, 32, 64, ... ran; 4 and 6 hung or aborted in backward
COMPILE_MIN_STEPS = 2000  # a compile costs 15-60 s on a 2-core VM; shorter runs do not win it back
COMPILE_DEADLINE_S = 300.0  # a first compile took 15-60 s on 2-core VMs; one 5x longer is taken for a hang
CUDA_COMPILE_MODE = "reduce-overhead"  # replays CUDA graphs: a step's hundreds of launches become one


@dataclass(frozen=True)
class StepPath:
    """How the training step runs, and why (recorded in the checkpoint and the demo's report)."""

    channels_last: bool
    precision: str  # "fp32" or "bf16" (CPU autocast); CUDA's fp16 autocast is train.amp
    compiled: bool
    reason: str

    def describe(self) -> str:
        layout = "channels_last" if self.channels_last else "NCHW"
        return f"{'compiled' if self.compiled else 'eager'}, {layout}, {self.precision} ({self.reason})"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags as Linux lists them (empty elsewhere: no native bf16 is assumed)."""
    return cpu_info()[1]


def has_native_bf16(flags: frozenset[str]) -> bool:
    return bool(flags & NATIVE_BF16_FLAGS)


def channels_last_is_safe(conv_widths: Sequence[int]) -> bool:
    return all(width % CHANNELS_LAST_WIDTH_MULTIPLE == 0 for width in conv_widths)


def choose_path(precision: str, compile_step: str, device: torch.device, planned_steps: int,
                flags: frozenset[str] | None = None, conv_widths: Sequence[int] = ()) -> StepPath:
    """The step's path for the settings on this device (``flags``: the CPU's, read from the machine by default;
    ``conv_widths``: the network's convolution widths)."""
    flags = cpu_flags() if flags is None else flags
    native_bf16 = device.type == "cpu" and has_native_bf16(flags)
    if device.type != "cpu" or precision == "fp32":
        chosen_precision, why = "fp32", "fp32 asked for" if precision == "fp32" else "CUDA: train.amp"
    elif precision == "bf16":
        chosen_precision, why = "bf16", "bf16 asked for"
    else:
        chosen_precision = "bf16" if native_bf16 else "fp32"
        why = "the CPU has native bf16" if native_bf16 else "no native bf16 on this CPU"
    if compile_step == "auto":
        compiled = native_bf16 and planned_steps >= COMPILE_MIN_STEPS
        why += "; compiled: native bf16 and a long run" if compiled else "; eager: compiling would not pay here"
    else:
        compiled = compile_step == "on"
        why += f"; {'compiled' if compiled else 'eager'} asked for"
    if compiled and device.type == "cuda":
        why += " (CUDA graphs)"
    channels_last = channels_last_is_safe(conv_widths)
    if not channels_last:
        why += f"; NCHW: conv widths not multiples of {CHANNELS_LAST_WIDTH_MULTIPLE}"
    return StepPath(channels_last=channels_last, precision=chosen_precision, compiled=compiled, reason=why)


def compiler_missing() -> str | None:
    """Why ``torch.compile`` cannot build CPU kernels here, or None when a C++ compiler is on the PATH."""
    if sys.platform == "win32":
        return "torch.compile has no CPU backend set up on Windows here"
    compilers = ("c++", "g++", "clang++")
    return None if any(shutil.which(name) for name in compilers) else "no C++ compiler (c++, g++, clang++) on PATH"


def eager_fallback(path: StepPath, why: str) -> StepPath:
    """The same path, eager; says why once (a warning the CLI prints as one line)."""
    warnings.warn(f"training eager instead of compiled: {why}", stacklevel=3)
    return StepPath(path.channels_last, path.precision, False, f"{path.reason}; fell back to eager: {why}")


class CompileTimeoutError(BaseException):
    """A compile ran past its deadline (a ``BaseException``: torch's ``except Exception`` neither swallows nor
    rewraps it)."""


class GuardedForward:
    """The model's forward, compiled where the path says so. A compile that fails, or that runs past
    :data:`COMPILE_DEADLINE_S`, falls back to the eager forward of the same model (the same weights), saying why in
    one line.

    torch compiles lazily, the forward on its first call with a new kind of input and the backward on its first
    backward; so each new kind of batch (shape, strides, dtype, grad mode) is first run once, forward and backward,
    under the deadline (a warm-up that leaves no gradient and restores the batch-norm statistics it moved), then the
    step itself runs compiled. The bound holds on the CPU, in the main thread; a CUDA backward runs on autograd's
    own threads and a DDP-wrapped model warms its forward only, so there the backward's compile is not bounded.
    """

    def __init__(self, model: nn.Module, path: StepPath) -> None:
        self.model, self.path = model, path
        self.compiled: Callable[[torch.Tensor], torch.Tensor] | None = None
        self._ready: set[tuple[Any, ...]] = set()  # kinds of batch compiled, forward and backward
        self.compile_s = 0.0  # seconds spent compiling so far (the demo's epoch fit does not repeat them per epoch)
        # CUDA graphs for one GPU; with DDP's gradient hooks they are untested, so a DDP model compiles without them.
        self.cuda_graphs = (any(weight.is_cuda for weight in model.parameters())
                            and not isinstance(model, nn.parallel.DistributedDataParallel))
        if path.compiled:
            missing = compiler_missing()
            if missing is None:
                self.compiled = torch.compile(model, **({"mode": CUDA_COMPILE_MODE} if self.cuda_graphs else {}))
            else:
                self.path = eager_fallback(path, missing)

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        if self.compiled is not None:
            try:
                kind = (tuple(images.shape), images.stride(), images.dtype, torch.is_grad_enabled())
                if kind not in self._ready:
                    started = time.perf_counter()
                    try:
                        with deadline(COMPILE_DEADLINE_S, CompileTimeoutError(f"{COMPILE_DEADLINE_S:g} s")):
                            self._warm_up(images)
                    finally:
                        self.compile_s += time.perf_counter() - started
                    self._ready.add(kind)
                if self.cuda_graphs:
                    torch.compiler.cudagraph_mark_step_begin()  # the last step's graph outputs may be reused
                return self.compiled(images)
            except CompileTimeoutError:
                self._fall_back(f"the compile took longer than {COMPILE_DEADLINE_S:g} s")
            except Exception as error:  # dynamo and inductor raise many types; any of them means: run eager
                self._fall_back(f"the compile failed ({first_line(error)})")
        return self.model(images)

    def _warm_up(self, images: torch.Tensor) -> None:
        """Compile forward and backward for this batch shape; weights, gradients and statistics stay as they were."""
        assert self.compiled is not None
        buffers = [(buffer, buffer.detach().clone()) for buffer in self.model.buffers()]
        try:
            output = self.compiled(images)
            if torch.is_grad_enabled() and not isinstance(self.model, nn.parallel.DistributedDataParallel):
                weights = [weight for weight in self.model.parameters() if weight.requires_grad]
                torch.autograd.grad(output.float().sum(), weights, allow_unused=True)  # DDP syncs only in steps
        finally:
            with torch.no_grad():
                for buffer, saved in buffers:
                    buffer.copy_(saved)

    def _fall_back(self, why: str) -> None:
        self.compiled = None
        self.path = eager_fallback(self.path, why)


def autocast(path: StepPath, device: torch.device, cuda_amp: bool) -> torch.autocast:
    """The forward's autocast context: bf16 on the CPU where the path says so, CUDA's fp16 with train.amp."""
    if device.type == "cpu":
        return torch.autocast("cpu", dtype=torch.bfloat16, enabled=path.precision == "bf16")
    return torch.autocast(device.type, enabled=cuda_amp)


def adam(parameters: Iterable[nn.Parameter], lr: float, device: torch.device) -> torch.optim.Adam:
    """Adam in its fused form where the device has it: one kernel over all parameters instead of a loop over
    them (the ``optimizer`` row of ``bench/results/training.md``); the same update up to rounding."""
    return torch.optim.Adam(parameters, lr=lr, fused=device.type in ("cpu", "cuda"))


def to_layout(images: torch.Tensor, path: StepPath) -> torch.Tensor:
    return images.contiguous(memory_format=torch.channels_last) if path.channels_last else images
