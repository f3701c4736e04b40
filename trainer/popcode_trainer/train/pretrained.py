"""Pretrained starts: a trunk trained on many generated parts (``popcode-train pretrain``), which a model of other
parts starts from instead of random weights (issue 53).

A start holds the weights of the network's ``features`` (convolutions) and ``hidden`` (MLP) for one network shape;
the output layer is not carried over, since each model's code describes its own parts' frames (what carries over
was measured: bench/results/pretrained-start.md). A start written from a trained model of the same parts and code
(``experiments.shipped_finetune``: the shipped models fine-tuned) also carries its output layer (``head``), which
then must fit the run's code exactly. ``train.init`` chooses the start:

- ``"auto"`` (the default): the shipped start for this run's network shape from the repository's ``models/``
  (:data:`SHIPPED_DIR`), if one is shipped; otherwise random weights, said in one line;
- ``"none"``: random weights (``--from-scratch``);
- a path: that start, refused in one line when it is not a start, is damaged, comes from a newer trainer or
  from another network shape -- never a silent random start.

The file format, its checks and ``init``'s choice are shared with the detector's starts
(:mod:`popcode_trainer.detection.start`): a :class:`StartKind` names which network a start is for.
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

START_VERSION = 1
TRANSFERRED_MODULES = ("features", "hidden")
OUTPUT_MODULE = "head"  # carried only by a start of a trained model of the same parts and code
SHIPPED_DIR = Path(__file__).resolve().parents[3] / "models"  # the repository's models/ (an editable install)
AUTO, NONE = "auto", "none"


@dataclass(frozen=True)
class StartKind:
    """Which network a start is for: its file's format field, its name in messages, the command that writes
    one, the name of a shipped one (``<prefix>-<shape id>.pt``), the settings section of its shape's fields and
    the setting that chooses it."""

    format: str
    what: str
    writer: str
    prefix: str
    shape_section: str
    init_setting: str


POSE_START = StartKind("popcode-pretrained-start", "pretrained start", "popcode-train pretrain", "pretrained-start",
                       "network", "train.init")
START_FORMAT = POSE_START.format


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


def shape_id(shape: NetworkConfig | dict[str, Any]) -> str:
    """A short name of a network shape (a pose network's config, or any start's shape fields), part of a shipped
    start's file name."""
    text = json.dumps(network_shape(shape) if isinstance(shape, NetworkConfig) else shape, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:10]


def shipped_path(config: NetworkConfig, folder: Path | None = None) -> Path:
    """Where the shipped start of this network shape lies in ``folder`` (default :data:`SHIPPED_DIR`); it may not
    exist."""
    return shipped_start_path(POSE_START, network_shape(config), folder)


def shipped_start_path(kind: StartKind, shape: dict[str, Any], folder: Path | None = None) -> Path:
    """Where the shipped ``kind`` start of this ``shape`` lies in ``folder`` (default :data:`SHIPPED_DIR`)."""
    return (SHIPPED_DIR if folder is None else folder) / f"{kind.prefix}-{shape_id(shape)}.pt"


def save_start(kind: StartKind, shape: dict[str, Any], state: dict[str, torch.Tensor], path: Path,
               card: dict[str, Any]) -> Path:
    """Save the weights a ``kind`` start carries, with the shape they fit and ``card``, atomically."""
    checkpoint.save_atomic({"format": kind.format, "version": START_VERSION, "network": shape, "state": state,
                            "card": card}, Path(path))
    return Path(path)


def write_start(model: nn.Module, config: NetworkConfig, path: Path, card: dict[str, Any]) -> Path:
    """Save ``model``'s transferred weights with ``card`` as a start, atomically."""
    state = {name: tensor.detach().cpu().clone() for name, tensor in model.state_dict().items()
             if name.split(".")[0] in TRANSFERRED_MODULES}
    return save_start(POSE_START, network_shape(config), state, path, card)


def read_start(path: str | Path, kind: StartKind = POSE_START) -> PretrainedStart:
    """A ``kind`` start file, checked; PopcodeError in one line for a file that is not one."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"{kind.what} not found: {path} ({kind.init_setting} is 'auto', 'none' or a start file)")
    state = checkpoint.load(path)
    if state.get("format") != kind.format:
        raise PopcodeError(f"{path} is not a {kind.what} ({kind.writer} writes them): it has no '{kind.format}' "
                           "format field")
    version = state.get("version")
    if not isinstance(version, int) or version < 1:
        raise PopcodeError(f"{path}: {kind.what} of unknown version {version!r}")
    if version > START_VERSION:
        raise PopcodeError(f"{path} is a {kind.what} of version {version}, newer than this trainer reads "
                           f"({START_VERSION}): update popcode, or pass --from-scratch")
    weights, network, card = state.get("state"), state.get("network"), state.get("card", {})
    if not isinstance(weights, dict) or not isinstance(network, dict) or not isinstance(card, dict) or \
            not all(isinstance(value, torch.Tensor) for value in weights.values()):
        raise PopcodeError(f"{path}: a damaged {kind.what} (its weights, network or card are missing)")
    return PretrainedStart(path, network, weights, card)


def check_fits(start: PretrainedStart, config: NetworkConfig) -> None:
    """Refuse, naming the differences, a start pretrained for another network shape than ``config``'s."""
    check_shape(start, network_shape(config), POSE_START)


def check_shape(start: PretrainedStart, wanted: dict[str, Any], kind: StartKind) -> None:
    """Refuse, naming the differences, a ``kind`` start made for another shape than ``wanted``."""
    differences = [f"{kind.shape_section}.{key} {start.network.get(key)!r} there, {wanted[key]!r} here"
                   for key in wanted if start.network.get(key) != wanted[key]]
    if differences:
        raise PopcodeError(f"{start.path} was pretrained for another network ({'; '.join(differences)}): pass a "
                           "start of this network, or --from-scratch")


def apply_start(model: nn.Module, start: PretrainedStart, config: NetworkConfig) -> int:
    """Copy the start's weights into ``model`` (built from ``config``); returns how many tensors were copied."""
    check_fits(start, config)
    own = model.state_dict()
    modules = TRANSFERRED_MODULES + ((OUTPUT_MODULE,) if carries_output_layer(start) else ())
    expected = {name for name in own if name.split(".")[0] in modules}
    if set(start.state) != expected:
        raise PopcodeError(f"{start.path}: its weights do not fit this network's {'/'.join(modules)} "
                           "(a damaged start, or one from another trainer): pass --from-scratch or another start")
    differing = [name for name in sorted(expected) if start.state[name].shape != own[name].shape]
    if differing:
        what = "output layer" if all(name.startswith(OUTPUT_MODULE + ".") for name in differing) else "weights"
        raise PopcodeError(f"{start.path}: its {what} ({differing[0]} {tuple(start.state[differing[0]].shape)}) "
                           f"do not fit this network's ({tuple(own[differing[0]].shape)}): a start with an output "
                           "layer fits only a run of the same code; pass --from-scratch or another start")
    model.load_state_dict(start.state, strict=False)
    return len(expected)


def carries_output_layer(start: PretrainedStart) -> bool:
    """Whether ``start`` also holds an output layer (a trained model's start, for fine-tuning it)."""
    return any(name.split(".")[0] == OUTPUT_MODULE for name in start.state)


def parameter_groups(model: nn.Module) -> list[dict[str, Any]]:
    """The optimizer's two groups when a start's weights may learn at their own rate: the weights a start fills
    (``lr_scale`` set when one is taken), then the rest (``lr_scale`` 1)."""
    transferred = [p for name, p in model.named_parameters() if name.split(".")[0] in TRANSFERRED_MODULES]
    rest = [p for name, p in model.named_parameters() if name.split(".")[0] not in TRANSFERRED_MODULES]
    return [{"params": transferred, "lr_scale": 1.0}, {"params": rest, "lr_scale": 1.0}]


def resolve_start(init: str, config: NetworkConfig) -> tuple[PretrainedStart | None, str]:
    """The start ``train.init`` names for a network of ``config``, and one line saying which start a run takes."""
    return resolve_kind_start(init, network_shape(config), POSE_START)


def resolve_kind_start(init: str, shape: dict[str, Any], kind: StartKind) -> tuple[PretrainedStart | None, str]:
    """The ``kind`` start an ``init`` setting names for a network of ``shape``, and one line saying which start a
    run takes: ``auto`` the shipped one of this shape if there is one, ``none`` none, else the file it names."""
    if init == NONE:
        return None, f"random weights ({kind.init_setting} 'none')"
    if init == AUTO:
        path = shipped_start_path(kind, shape)
        if not path.is_file():
            return None, f"random weights: no {kind.what} is shipped for this network shape ({path.name})"
        start = read_start(path, kind)
        return start, f"the shipped {kind.what} {path.name} ({describe(start)})"
    start = read_start(init, kind)
    check_shape(start, shape, kind)
    return start, f"the {kind.what} {init} ({describe(start)})"


def describe(start: PretrainedStart) -> str:
    """What a start saw, from its card: "312 generated parts, 18 epochs, commit abc1234", or for a trained model's
    weights "the weights of model.onnx, 90 epochs, commit abc1234"."""
    card = start.card
    trained = f"{card.get('epochs', '?')} epochs, commit {card.get('commit', '?')}"
    if "from_model" in card:  # a trained model's own weights (experiments.shipped_start)
        return f"the weights of {Path(card['from_model']).name}, {trained}"
    return f"{card.get('parts', '?')} generated parts, {trained}"
