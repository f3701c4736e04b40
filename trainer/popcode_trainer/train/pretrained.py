"""Pretrained starts: a trunk trained on many generated parts (``popcode-train pretrain``), which a model of other
parts starts from instead of random weights (issue 53).

A start holds the weights of the network's ``features`` (convolutions) and ``hidden`` (MLP) for one network shape;
the output layer is not carried over, since each model's code describes its own parts' frames (what carries over
was measured: bench/results/pretrained-start.md). ``train.init`` chooses the start:

- ``"auto"`` (the default): the shipped start for this run's network shape from the repository's ``models/``
  (:data:`SHIPPED_DIR`), if one is shipped; otherwise random weights, said in one line;
- ``"none"``: random weights (``--from-scratch``);
- a path: that start, refused in one line when it is not a start, is damaged, comes from a newer trainer or
  from another network shape -- never a silent random start.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from popcode_runtime.base.errors import PopcodeError

from . import checkpoint
from .network import NetworkConfig

START_FORMAT = "popcode-pretrained-start"
START_VERSION = 1
TRANSFERRED_MODULES = ("features", "hidden")
SHIPPED_DIR = Path(__file__).resolve().parents[3] / "models"  # the repository's models/ (an editable install)
AUTO, NONE = "auto", "none"


@dataclass(frozen=True)
class PretrainedStart:
    """The transferred weights of one network shape and the card that says where they came from."""

    path: Path
    network: dict[str, Any]  # NetworkConfig fields without output_dim: what must match
    state: dict[str, torch.Tensor]
    card: dict[str, Any]


def network_shape(config: NetworkConfig) -> dict[str, Any]:
    """The fields of a network config the transferred weights depend on (all but the output layer's width)."""
    shape = dataclasses.asdict(config)
    shape.pop("output_dim")
    return json.loads(json.dumps(shape))  # tuples as lists, as the file stores them


def shape_id(config: NetworkConfig) -> str:
    """A short name of a network shape, part of a shipped start's file name."""
    text = json.dumps(network_shape(config), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:10]


def shipped_path(config: NetworkConfig, folder: Path | None = None) -> Path:
    """Where the shipped start of this network shape lies in ``folder`` (default :data:`SHIPPED_DIR`); it may not
    exist."""
    return (SHIPPED_DIR if folder is None else folder) / f"pretrained-start-{shape_id(config)}.pt"


def write_start(model: nn.Module, config: NetworkConfig, path: Path, card: dict[str, Any]) -> Path:
    """Save ``model``'s transferred weights with ``card`` as a start, atomically."""
    state = {name: tensor.detach().cpu().clone() for name, tensor in model.state_dict().items()
             if name.split(".")[0] in TRANSFERRED_MODULES}
    checkpoint.save_atomic({"format": START_FORMAT, "version": START_VERSION, "network": network_shape(config),
                            "state": state, "card": card}, Path(path))
    return Path(path)


def read_start(path: str | Path) -> PretrainedStart:
    """A start file, checked; PopcodeError in one line for a file that is not one."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"pretrained start not found: {path} (train.init is 'auto', 'none' or a start file)")
    state = checkpoint.load(path)
    if state.get("format") != START_FORMAT:
        raise PopcodeError(f"{path} is not a pretrained start (popcode-train pretrain writes them): it has no "
                           f"'{START_FORMAT}' format field")
    version = state.get("version")
    if not isinstance(version, int) or version < 1:
        raise PopcodeError(f"{path}: pretrained start of unknown version {version!r}")
    if version > START_VERSION:
        raise PopcodeError(f"{path} is a pretrained start of version {version}, newer than this trainer reads "
                           f"({START_VERSION}): update popcode, or pass --from-scratch")
    weights, network, card = state.get("state"), state.get("network"), state.get("card", {})
    if not isinstance(weights, dict) or not isinstance(network, dict) or not isinstance(card, dict) or \
            not all(isinstance(value, torch.Tensor) for value in weights.values()):
        raise PopcodeError(f"{path}: a damaged pretrained start (its weights, network or card are missing)")
    return PretrainedStart(path, network, weights, card)


def check_fits(start: PretrainedStart, config: NetworkConfig) -> None:
    """Refuse, naming the differences, a start pretrained for another network shape than ``config``'s."""
    wanted = network_shape(config)
    differences = [f"network.{key} {start.network.get(key)!r} there, {wanted[key]!r} here" for key in wanted
                   if start.network.get(key) != wanted[key]]
    if differences:
        raise PopcodeError(f"{start.path} was pretrained for another network ({'; '.join(differences)}): pass a "
                           "start of this network, or --from-scratch")


def apply_start(model: nn.Module, start: PretrainedStart, config: NetworkConfig) -> int:
    """Copy the start's weights into ``model`` (built from ``config``); returns how many tensors were copied."""
    check_fits(start, config)
    own = model.state_dict()
    expected = {name for name in own if name.split(".")[0] in TRANSFERRED_MODULES}
    if set(start.state) != expected or any(start.state[name].shape != own[name].shape for name in expected):
        raise PopcodeError(f"{start.path}: its weights do not fit this network's {'/'.join(TRANSFERRED_MODULES)} "
                           "(a damaged start, or one from another trainer): pass --from-scratch or another start")
    model.load_state_dict(start.state, strict=False)
    return len(expected)


def parameter_groups(model: nn.Module) -> list[dict[str, Any]]:
    """The optimizer's two groups when a start's weights may learn at their own rate: the weights a start fills
    (``lr_scale`` set when one is taken), then the rest (``lr_scale`` 1)."""
    transferred = [p for name, p in model.named_parameters() if name.split(".")[0] in TRANSFERRED_MODULES]
    rest = [p for name, p in model.named_parameters() if name.split(".")[0] not in TRANSFERRED_MODULES]
    return [{"params": transferred, "lr_scale": 1.0}, {"params": rest, "lr_scale": 1.0}]


def resolve_start(init: str, config: NetworkConfig) -> tuple[PretrainedStart | None, str]:
    """The start ``train.init`` names for a network of ``config``, and one line saying which start a run takes."""
    if init == NONE:
        return None, "random weights (train.init 'none')"
    if init == AUTO:
        path = shipped_path(config)
        if not path.is_file():
            return None, f"random weights: no pretrained start is shipped for this network shape ({path.name})"
        start = read_start(path)
        return start, f"the shipped pretrained start {path.name} ({describe(start)})"
    start = read_start(init)
    check_fits(start, config)
    return start, f"the pretrained start {init} ({describe(start)})"


def describe(start: PretrainedStart) -> str:
    """What a start saw, from its card: "312 generated parts, 18 epochs, commit abc1234"."""
    card = start.card
    parts = card.get("parts", "?")
    return f"{parts} generated parts, {card.get('epochs', '?')} epochs, commit {card.get('commit', '?')}"
