"""The paper's networks (section III-B and the toy network of section IV-A).

Widths are not given in the paper. The defaults of :class:`NetworkConfig` follow
the Augmented Autoencoder encoder that the paper names as its inspiration:
5x5 convolutions with stride 2 and 128/256/256 channels take the 128x128 crop
to 16x16. The 1x1 fourth convolution (GELU, after ConvNeXt) squeezes the 256
channels to 32, so the flattened feature is 8192 wide and the first linear
layer stays small (8.4 M weights instead of 67 M for 256 channels). The
hidden widths 1024/512/256 narrow towards a 256-wide bottleneck: the target
code is a smooth sum of a few Gaussian bumps, so 256 numbers describe it
easily, and the output layer -- 256 x 92,232 = 23.6 M weights, by far the
largest -- stays within what an edge device reads per crop in a few
milliseconds (94 MB fp32, 24 MB int8).

The output layer is a plain ``x @ W + b`` with ``W`` stored as ``(in, out)``
so that ONNX export writes ``MatMul`` + ``Add`` rather than ``Gemm``: the
weight-only ``MatMulNBits`` quantiser only rewrites ``MatMul`` nodes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from popcode_runtime.base.errors import PopcodeError

CONTRAST_EPS = 1e-3  # a flat crop (std 0) stays finite after normalisation
MAX_DENSE_PARAMETERS = 10**9  # 16 GB with Adam's two moments and the gradient; the paper's network has 35.2 M


@dataclass(frozen=True)
class NetworkConfig:
    """Shape of the paper's network; stored in every checkpoint so export rebuilds it exactly."""

    output_dim: int = 2562 * 36
    input_size: int = 128
    conv_channels: tuple[int, int, int] = (128, 256, 256)
    conv_kernel: int = 5
    squeeze_channels: int = 32  # the 1x1 fourth convolution
    hidden: tuple[int, int, int] = (1024, 512, 256)
    leaky_slope: float = 0.01
    trunk: str = "paper"  # "paper": one strided conv per stage; "residual": a 3x3 stem and ResNet basic blocks


@dataclass(frozen=True)
class ToyNetworkConfig:
    """The 1-D toy network of section IV-A: 64x64 input, 3 conv + max-pool, 4 linear, ReLU."""

    output_dim: int = 36
    input_size: int = 64
    conv_channels: tuple[int, int, int] = (32, 64, 128)
    hidden: tuple[int, int, int] = (256, 256, 256)


def contrast_normalise(image: torch.Tensor) -> torch.Tensor:
    """Zero mean, unit standard deviation per crop (paper IV-D); part of the exported graph."""
    mean = image.mean(dim=(1, 2, 3), keepdim=True)
    centred = image - mean
    std = centred.pow(2).mean(dim=(1, 2, 3), keepdim=True).sqrt()
    return centred / (std + CONTRAST_EPS)


class OutputLayer(nn.Module):
    """``x @ W + b`` with ``W`` ``(in, out)``; exports as MatMul + Add."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(in_features, out_features))
        self.bias = nn.Parameter(torch.empty(out_features))
        bound = 1.0 / math.sqrt(in_features)  # nn.Linear's default initialisation
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.weight + self.bias


class ColumnBlockOutputLayer(nn.Module):
    """An :class:`OutputLayer` cut into column blocks of at most ``block`` outputs, concatenated.

    Same result; each block is its own weight in the exported graph, so no
    tensor exceeds the 16384 limit of onnxruntime's CoreML provider.
    """

    def __init__(self, layer: OutputLayer, block: int) -> None:
        super().__init__()
        self.weights = nn.ParameterList([nn.Parameter(w.detach().clone()) for w in layer.weight.split(block, 1)])
        self.biases = nn.ParameterList([nn.Parameter(b.detach().clone()) for b in layer.bias.split(block)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x @ w + b for w, b in zip(self.weights, self.biases, strict=True)], dim=1)


def _mlp(widths: list[int], activation: type[nn.Module] | nn.Module) -> nn.Sequential:
    layers: list[nn.Module] = []
    for fan_in, fan_out in zip(widths[:-1], widths[1:], strict=True):
        layers += [nn.Linear(fan_in, fan_out), activation() if isinstance(activation, type) else activation]
    return nn.Sequential(*layers)


class _CropNet(nn.Module):
    """Shared shape of both networks: normalise, ``features`` (convs), ``hidden`` (MLP), ``head``."""

    features: nn.Module
    hidden: nn.Module
    head: nn.Module

    def __init__(self) -> None:
        super().__init__()
        self.output_activation: nn.Module | None = None  # set when loaded for export (model_io), never in training

    def forward_features(self, image: torch.Tensor) -> torch.Tensor:
        return self.features(contrast_normalise(image)).flatten(1)

    def forward_head(self, features: torch.Tensor) -> torch.Tensor:
        output = self.head(self.hidden(features))
        return output if self.output_activation is None else self.output_activation(output)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.forward_head(self.forward_features(image))


TRUNKS = ("paper", "residual")


def _conv_bn(fan_in: int, fan_out: int, kernel: int, stride: int) -> list[nn.Module]:
    return [nn.Conv2d(fan_in, fan_out, kernel, stride=stride, padding=kernel // 2, bias=False),
            nn.BatchNorm2d(fan_out)]


class ResidualBlock(nn.Module):
    """ResNet's basic block, downsampling by 2: two 3x3 convs beside a strided 1x1 shortcut."""

    def __init__(self, fan_in: int, fan_out: int) -> None:
        super().__init__()
        self.body = nn.Sequential(*_conv_bn(fan_in, fan_out, 3, 2), nn.ReLU(inplace=True),
                                  *_conv_bn(fan_out, fan_out, 3, 1))
        self.shortcut = nn.Sequential(*_conv_bn(fan_in, fan_out, 1, 2))
        self.activation = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.activation(self.body(x) + self.shortcut(x))


def _paper_stages(config: NetworkConfig) -> list[nn.Module]:
    """One ``conv_kernel`` conv of stride 2 + BatchNorm + ReLU per width (the AAE encoder's shape)."""
    layers: list[nn.Module] = []
    channels = 1
    for width in config.conv_channels:
        layers += [*_conv_bn(channels, width, config.conv_kernel, 2), nn.ReLU(inplace=True)]
        channels = width
    return layers


def _residual_stages(config: NetworkConfig) -> list[nn.Module]:
    """A 3x3 stride-2 stem of the first width, then a downsampling basic block per width.

    One more halving than the paper trunk (stem + blocks): the features end at 1/16 of the crop.
    """
    first = config.conv_channels[0]
    layers: list[nn.Module] = [*_conv_bn(1, first, 3, 2), nn.ReLU(inplace=True)]
    channels = first
    for width in config.conv_channels:
        layers.append(ResidualBlock(channels, width))
        channels = width
    return layers


def feature_side(config: NetworkConfig) -> int:
    """The side of the trunk's output for a crop of ``config.input_size``: each stride-2 conv (padding
    ``kernel // 2``) maps ``s`` to ``(s + 2 (kernel // 2) - kernel) // 2 + 1``, which halves only even sides
    and odd kernels exactly."""
    kernels = [3] * (len(config.conv_channels) + 1) if config.trunk == "residual" else \
        [config.conv_kernel] * len(config.conv_channels)
    side = config.input_size
    for kernel in kernels:
        side = (side + 2 * (kernel // 2) - kernel) // 2 + 1
    return side


def dense_parameters(config: NetworkConfig) -> int:
    """Weights and biases of the hidden layers and the output layer (the bulk of the network)."""
    widths = [config.squeeze_channels * feature_side(config) ** 2, *config.hidden, config.output_dim]
    return sum(fan_in * fan_out + fan_out for fan_in, fan_out in zip(widths[:-1], widths[1:], strict=True))


def _check_dense(config: NetworkConfig) -> None:
    if dense_parameters(config) > MAX_DENSE_PARAMETERS:
        raise PopcodeError(f"network of {dense_parameters(config):,} dense parameters, more than the limit of "
                           f"{MAX_DENSE_PARAMETERS:,} (the paper's has 35 M): lower network.hidden, "
                           f"network.squeeze_channels or the code size")


def check_trainable(config: NetworkConfig, rank_batch: int) -> None:
    """Refuse, in one line, a network too large to build or one a rank's batch of ``rank_batch`` crops cannot train
    (a trunk that ends at 1x1 with one crop: BatchNorm needs two). Checked before the crops are cached, so the line
    comes before any progress bar, and again when training starts."""
    _check_dense(config)
    if rank_batch == 1 and feature_side(config) == 1:
        raise PopcodeError(f"the trunk ends at 1x1 for data.crop_size {config.input_size}, where BatchNorm needs "
                           f"two crops per rank: raise train.batch_size or data.crop_size")


class PopcodeNet(_CropNet):
    """Grey crop ``(N, 1, S, S)`` in [0, 1] -> output ``(N, output_dim)`` (paper section III-B)."""

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        if config.trunk not in TRUNKS:
            raise ValueError(f"unknown trunk {config.trunk!r}; choose one of {list(TRUNKS)}")
        self.config = config
        stages = _residual_stages(config) if config.trunk == "residual" else _paper_stages(config)
        squeeze = [nn.Conv2d(config.conv_channels[-1], config.squeeze_channels, 1), nn.GELU()]
        self.features = nn.Sequential(*stages, *squeeze)
        _check_dense(config)
        flat = config.squeeze_channels * feature_side(config) ** 2
        self.hidden = _mlp([flat, *config.hidden], nn.LeakyReLU(config.leaky_slope))
        self.head = OutputLayer(config.hidden[-1], config.output_dim)



class ToyNet(_CropNet):
    """The toy experiment's network (section IV-A): one angle from a 64x64 image."""

    def __init__(self, config: ToyNetworkConfig) -> None:
        super().__init__()
        self.config = config
        convs: list[nn.Module] = []
        channels = 1
        for width in config.conv_channels:
            convs += [nn.Conv2d(channels, width, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(2)]
            channels = width
        self.features = nn.Sequential(*convs)
        side = config.input_size // 2 ** len(config.conv_channels)
        self.hidden = _mlp([channels * side * side, *config.hidden], nn.ReLU)
        self.head = OutputLayer(config.hidden[-1], config.output_dim)



def count_macs(model: nn.Module, input_size: int) -> int:
    """Multiply-accumulates of one forward pass on one crop (convolutions, linear layers, output layer)."""
    total = 0

    def conv_hook(module: nn.Conv2d, _inputs: tuple, output: torch.Tensor) -> None:
        nonlocal total
        kernel = module.kernel_size[0] * module.kernel_size[1] * module.in_channels // module.groups
        total += output[0].numel() * kernel

    def linear_hook(module: nn.Module, inputs: tuple, output: torch.Tensor) -> None:
        nonlocal total
        total += inputs[0].shape[-1] * output.shape[-1]

    hooks = []
    for module in model.modules():
        if isinstance(module, nn.Conv2d):
            hooks.append(module.register_forward_hook(conv_hook))
        elif isinstance(module, nn.Linear | OutputLayer):
            hooks.append(module.register_forward_hook(linear_hook))
    was_training = model.training
    model.eval()
    with torch.no_grad():
        model(torch.zeros(1, 1, input_size, input_size))
    model.train(was_training)
    for hook in hooks:
        hook.remove()
    return total


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())



def build_network(config: NetworkConfig | ToyNetworkConfig) -> nn.Module:
    """The network a config describes (the checkpoint stores the config, export calls this)."""
    return ToyNet(config) if isinstance(config, ToyNetworkConfig) else PopcodeNet(config)
