"""Network shapes, the contrast normalisation inside the model, and the MAC count."""

from __future__ import annotations

import torch

from popcode_trainer.network import (
    ColumnBlockOutputLayer,
    NetworkConfig,
    PopcodeNet,
    ToyNet,
    ToyNetworkConfig,
    count_macs,
    count_parameters,
)

TINY = NetworkConfig(output_dim=504, conv_channels=(8, 8, 8), squeeze_channels=4, hidden=(32, 32, 32))


def test_shapes() -> None:
    torch.manual_seed(0)
    assert PopcodeNet(TINY)(torch.rand(3, 1, 128, 128)).shape == (3, 504)
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
