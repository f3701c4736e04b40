"""Network shapes, the contrast normalisation inside the model, and the MAC count."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from popcode_runtime.base.errors import PopcodeError
from popcode_trainer.train.network import (
    ColumnBlockOutputLayer,
    NetworkConfig,
    PopcodeNet,
    ToyNet,
    ToyNetworkConfig,
    build_network,
    count_macs,
    count_parameters,
)

TINY = NetworkConfig(output_dim=504, conv_channels=(8, 8, 8), squeeze_channels=4, hidden=(32, 32, 32))
TINY_RESIDUAL = replace(TINY, trunk="residual", conv_channels=(8, 8, 16))


def test_shapes() -> None:
    torch.manual_seed(0)
    assert PopcodeNet(TINY)(torch.rand(3, 1, 128, 128)).shape == (3, 504)
    assert PopcodeNet(TINY_RESIDUAL)(torch.rand(3, 1, 128, 128)).shape == (3, 504)
    assert PopcodeNet(replace(TINY_RESIDUAL, input_size=64))(torch.rand(2, 1, 64, 64)).shape == (2, 504)
    assert ToyNet(ToyNetworkConfig())(torch.rand(2, 1, 64, 64)).shape == (2, 36)


def test_output_ignores_brightness_and_contrast() -> None:
    torch.manual_seed(0)
    model = PopcodeNet(TINY).eval()
    image = torch.rand(2, 1, 128, 128)
    with torch.no_grad():
        assert torch.allclose(model(image), model(0.5 * image + 0.2), atol=1e-4)


def test_column_blocks_give_the_same_output() -> None:
    torch.manual_seed(0)
    model = PopcodeNet(TINY)
    x = torch.rand(4, 32)
    assert torch.allclose(ColumnBlockOutputLayer(model.head, 100)(x), model.head(x), atol=1e-6)


def test_macs_match_the_analytic_count() -> None:
    model = PopcodeNet(TINY)
    convs = 64 * 64 * 8 * 25 * 1 + 32 * 32 * 8 * 25 * 8 + 16 * 16 * 8 * 25 * 8 + 16 * 16 * 4 * 8
    linear = 1024 * 32 + 32 * 32 + 32 * 32 + 32 * 504
    assert count_macs(model, 128) == convs + linear
    assert count_parameters(model) == sum(p.numel() for p in model.parameters())


def test_residual_trunk_macs_match_the_analytic_count() -> None:
    model = PopcodeNet(TINY_RESIDUAL)
    stem = 64 * 64 * 8 * 9
    blocks = [(8, 8, 32), (8, 8, 16), (8, 16, 8)]  # fan in, fan out, output side
    convs = sum(side * side * out * (9 * fan_in + 9 * out + fan_in) for fan_in, out, side in blocks)
    squeeze = 8 * 8 * 4 * 16
    linear = 256 * 32 + 32 * 32 + 32 * 32 + 32 * 504
    assert count_macs(model, 128) == stem + convs + squeeze + linear


def test_residual_blocks_pass_the_shortcut() -> None:
    """With the body silenced, a block is ReLU(BN(1x1 strided conv)): the shortcut alone carries the signal."""
    torch.manual_seed(0)
    block = PopcodeNet(TINY_RESIDUAL).features[3]  # stem conv, BN, ReLU, then the first block
    torch.nn.init.zeros_(block.body[-1].weight)  # the last BatchNorm's scale: the body adds nothing
    block.eval()
    x = torch.rand(2, 8, 16, 16)
    with torch.no_grad():
        assert torch.allclose(block(x), torch.relu(block.shortcut(x)))


def test_unknown_trunk_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown trunk 'vit'"):
        build_network(replace(TINY, trunk="vit"))


@pytest.mark.parametrize(("base", "input_size", "kernel"), [(TINY, 13, 5), (TINY, 100, 4), (TINY, 40, 36),
                                                             (TINY_RESIDUAL, 37, 5)])
def test_the_hidden_layers_fit_the_trunk_for_any_crop_and_kernel(base, input_size: int, kernel: int) -> None:
    """Odd crop sides and even kernels do not halve exactly, and a kernel may be wider than the map it slides over
    (36 over 21 and 11 pixels; 100 over 128 took 8 s of convolution for the same arithmetic): the first dense
    layer is sized by the conv arithmetic."""
    config = replace(base, input_size=input_size, conv_kernel=kernel)
    assert PopcodeNet(config)(torch.rand(2, 1, input_size, input_size)).shape == (2, 504)


def test_a_network_too_large_to_hold_is_refused_before_it_is_allocated() -> None:
    with pytest.raises(PopcodeError, match="more than the limit of 1,000,000,000"):
        PopcodeNet(replace(TINY, hidden=(10**8, 32, 32)))
