"""Training configuration: typed dataclasses read from TOML, with ``section.key=value`` overrides.

Defaults are the paper's (section IV-D): Adam, lr 2e-4, batch 64, 80 epochs,
code 2562 x 36 with sigma 20 deg. Every unknown section, key or choice is an
error that names the valid ones; a checkpoint stores :meth:`Config.to_dict`,
so resume and export see exactly the configuration that trained the model.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.population_code import PAPER_N_ANGLES, PAPER_N_AXES, PAPER_SIGMA_DEG
from popcode_runtime.geometry.crop import CROP_SIZE
from popcode_runtime.model.metadata import MAX_INPUT_SIZE, MIN_INPUT_SIZE, Representation, RotationFrame

from ..data.box_noise import box_noise_preset
from .fast_path import COMPILE_CHOICES, PRECISIONS
from .network import TRUNKS, NetworkConfig
from .representations import LOSSES
from .schedule import SCHEDULES

if sys.version_info >= (3, 11):
    import tomllib
else:  # the same parser, from PyPI, before Python 3.11
    import tomli as tomllib

BOX_KINDS = ("bbox_obj", "bbox_visib")
BACKGROUND_POLICIES = ("auto", "always", "never")  # where rendered crops get a pasted background (samples.py)
DEVICES = ("auto", "cpu", "cuda")
MAX_CONV_CHANNELS = 4096  # the paper's widest is 256
# The paper trains 80; each epoch writes a metrics.csv row and may write a checkpoint, and the schedule and the
# demo's time estimate are sized by the count, so a count of 10^20 is a typo, refused before any work.
MAX_EPOCHS = 100_000
# Network fields that follow from the representation and the crop, not from the user.
DERIVED_NETWORK_FIELDS = ("output_dim", "input_size")


@dataclass(frozen=True)
class DataConfig:
    """Where the crops come from. ``obj_ids`` empty: every object in the splits, pooled."""

    splits: tuple[str, ...] = ()
    split_weights: tuple[float, ...] = ()  # share of each split in an epoch's crops; empty: every crop once
    models_dir: str = ""
    obj_ids: tuple[int, ...] = ()
    min_visib_fract: float = 0.6
    box: str = "bbox_obj"
    val_fraction: float = 0.1
    augment: bool = True
    occlusion_p: float = 0.0  # rendered crops: probability of an occluder over part of the object (not the paper's)
    noise_sigma: float = 0.02  # Gaussian grain on crops (intensities in [0, 1]), the paper's strength ...
    noise_p: float = 0.5  # ... and probability; stronger grain is a lever against the renderer's clean look
    background: str = "auto"  # "auto": pasted behind single-object renders, scenes keep their own clutter
    box_noise: str = "none"  # training crops from detector-like boxes: a preset of data.box_noise
    box_noise_p: float = 1.0  # the share of training crops cut from such a box (the rest: the true box)
    crop_size: int = CROP_SIZE
    num_workers: int = 2
    cache_dir: str = ""  # the crop cache's folder; empty: crop_cache/ in train.out_dir (runs of a split may share one)


@dataclass(frozen=True)
class CodeConfig:
    """The population-code grid (also the one-hot baseline's classes)."""

    n_axes: int = PAPER_N_AXES
    n_angles: int = PAPER_N_ANGLES
    sigma_deg: float = PAPER_SIGMA_DEG
    sigma_from_symmetries: bool = False  # narrow sigma_deg until symmetric peaks stay apart (code_sigma)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and the output representation."""

    representation: str = Representation.POPULATION_CODE
    loss: str = "mse"  # population code: "mse" (the paper's), "cross_entropy" or both (representations.LOSSES)
    rotation_frame: str = RotationFrame.EGOCENTRIC
    num_hypotheses: int = 20  # M of the multi_hypothesis baseline
    epochs: int = 80
    batch_size: int = 64  # global: split evenly over torchrun ranks
    lr: float = 2e-4
    schedule: str = "constant"  # the rate over the run: "constant" (the paper's), "cosine", "anneal" (schedule.py)
    warmup_epochs: float = 0.0  # linear warm-up from 0 to lr over this many epochs (any schedule)
    seed: int = 0
    out_dir: str = "runs/popcode"
    device: str = "auto"
    amp: bool = True  # mixed precision; used on CUDA only
    precision: str = "auto"  # CPU: "auto" (bf16 where the CPU has it natively), "fp32", "bf16" (fast_path.py)
    compile: str = "auto"  # "auto" (where it pays), "on", "off": torch.compile of the step (fast_path.py)
    # the first weights: "auto" (the shipped pretrained start of this network shape, if any), "none" (random) or a
    # start file of popcode-train pretrain (train/pretrained.py)
    init: str = "auto"
    # with a pretrained start: the rate of the weights it filled (features, hidden) as a share of lr (1: the same)
    init_lr_scale: float = 1.0


@dataclass(frozen=True)
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    code: CodeConfig = field(default_factory=CodeConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain dict (lists, no tuples) with derived network fields left out; TOML/JSON friendly."""
        data = {name: _plain(dataclasses.asdict(getattr(self, name))) for name in SECTIONS}
        for key in DERIVED_NETWORK_FIELDS:
            data["network"].pop(key)
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Config:
        unknown = sorted(set(data) - set(SECTIONS))
        if unknown:
            raise PopcodeError(f"unknown config section(s) {unknown}; valid sections: {list(SECTIONS)}")
        sections = {name: _build_section(name, data.get(name, {})) for name in SECTIONS}
        config = cls(**sections)
        _check_choices(config)
        return config


SECTIONS: dict[str, type] = {"data": DataConfig, "code": CodeConfig, "network": NetworkConfig, "train": TrainConfig}
PATH_SETTINGS = (("data", "splits"), ("data", "models_dir"), ("data", "cache_dir"), ("train", "out_dir"))


def _plain(value: Any) -> Any:
    if isinstance(value, enum.Enum):  # checkpoints are read with weights_only: plain types only
        return value.value
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _settable_fields(section: str) -> list[str]:
    names = [f.name for f in dataclasses.fields(SECTIONS[section])]
    return [n for n in names if not (section == "network" and n in DERIVED_NETWORK_FIELDS)]


def _build_section(section: str, table: Any) -> Any:
    if not isinstance(table, Mapping):
        raise PopcodeError(f"config section [{section}] must be a table, got {table!r}")
    valid = _settable_fields(section)
    unknown = sorted(set(table) - set(valid))
    if unknown:
        raise PopcodeError(f"unknown config key(s) {[f'{section}.{k}' for k in unknown]}; "
                           f"valid keys in [{section}]: {valid}")
    return SECTIONS[section](**typed_values(SECTIONS[section], table, section))


def typed_values(fields: type, table: Mapping[str, Any], section: str) -> dict[str, Any]:
    """``table``'s values checked against the types of the dataclass ``fields`` (an int field takes an integer
    only, a float field any finite number, a str field text), named ``section.key`` in the one-line error: the one
    type check of every config file and ``--set``, the pose model's and the detector's."""
    hints = typing.get_type_hints(fields)
    return {key: _coerce(value, hints[key], f"{section}.{key}") for key, value in table.items()}


def _coerce(value: Any, hint: Any, name: str) -> Any:
    """Check ``value`` against a field's type hint; TOML arrays become tuples, ints may be floats."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise PopcodeError(f"{name} must be a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], name) for v in value)
        if len(value) != len(args):
            raise PopcodeError(f"{name} must have {len(args)} entries, got {len(value)}")
        return tuple(_coerce(v, a, name) for v, a in zip(value, args, strict=True))
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _coerce(value, next(a for a in args if a is not type(None)), name)
    if hint is float and isinstance(value, int | float) and not isinstance(value, bool):
        if not math.isfinite(value):
            raise PopcodeError(f"{name} must be a finite number, got {value!r}")
        return float(value)
    if hint is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if hint in (bool, str) and isinstance(value, hint):
        return value
    raise PopcodeError(f"{name} must be {getattr(hint, '__name__', hint)}, got {value!r}")


def _choice(name: str, value: str, choices: Sequence[str]) -> None:
    if value not in choices:
        raise PopcodeError(f"{name} = {value!r} is not valid; choose one of {list(choices)}")


def _check_choices(config: Config) -> None:
    _choice("train.representation", config.train.representation, Representation.values())
    _choice("train.rotation_frame", config.train.rotation_frame, RotationFrame.values())
    _choice("train.device", config.train.device, DEVICES)
    _choice("data.box", config.data.box, BOX_KINDS)
    _choice("network.trunk", config.network.trunk, TRUNKS)
    _choice("train.schedule", config.train.schedule, SCHEDULES)
    _choice("train.loss", config.train.loss, LOSSES)
    _choice("train.precision", config.train.precision, PRECISIONS)
    _choice("train.compile", config.train.compile, COMPILE_CHOICES)
    if config.train.loss != "mse" and config.train.representation != Representation.POPULATION_CODE:
        raise PopcodeError(f"train.loss = {config.train.loss!r} applies to the population code; "
                           f"{config.train.representation} has its own loss: add --set train.loss='\"mse\"'")
    _choice("data.background", config.data.background, BACKGROUND_POLICIES)
    try:
        box_noise_preset(config.data.box_noise)
    except PopcodeError as error:
        raise PopcodeError(f"data.box_noise: {error}") from error
    if not 0.0 < config.data.box_noise_p <= 1.0:  # NaN too
        raise PopcodeError(f"data.box_noise_p must lie in (0, 1], got {config.data.box_noise_p}")
    weights = config.data.split_weights
    if weights and len(weights) != len(config.data.splits):
        raise PopcodeError(f"data.split_weights has {len(weights)} entries for {len(config.data.splits)} "
                           "data.splits: give one weight per split, or none")
    if any(not weight > 0 for weight in weights):  # NaN too
        raise PopcodeError(f"data.split_weights must all be positive (a split you do not want: leave it out of "
                           f"data.splits), got {list(weights)}")
    if not 0.0 <= config.data.val_fraction < 1.0:
        raise PopcodeError(f"data.val_fraction must lie in [0, 1), got {config.data.val_fraction}")
    for key in ("epochs", "batch_size", "num_hypotheses"):
        if getattr(config.train, key) < 1:
            raise PopcodeError(f"train.{key} must be at least 1")
    if config.train.epochs > MAX_EPOCHS:
        raise PopcodeError(f"train.epochs must be at most {MAX_EPOCHS:,} (the paper trains 80), got "
                           f"{config.train.epochs:,}")
    if not 0 <= config.train.seed < 2**63:  # numpy's and torch's generators take no negative seed
        raise PopcodeError(f"train.seed must lie in [0, 2^63), got {config.train.seed}")
    if config.data.num_workers < 0:
        raise PopcodeError(f"data.num_workers must be at least 0 (0: load in the main process), got "
                           f"{config.data.num_workers}")
    if not MIN_INPUT_SIZE <= config.data.crop_size <= MAX_INPUT_SIZE:
        raise PopcodeError(f"data.crop_size must lie in [{MIN_INPUT_SIZE}, {MAX_INPUT_SIZE}] px (the runtime's "
                           f"limits), got {config.data.crop_size}")
    if config.train.lr <= 0:
        raise PopcodeError("train.lr must be positive")
    if not 0.0 < config.train.init_lr_scale <= 1.0:  # NaN too
        raise PopcodeError(f"train.init_lr_scale must lie in (0, 1], got {config.train.init_lr_scale}")
    if not 0.0 <= config.train.warmup_epochs <= config.train.epochs:
        raise PopcodeError(f"train.warmup_epochs must lie in [0, train.epochs = {config.train.epochs}], got "
                           f"{config.train.warmup_epochs}")
    network = config.network
    for key in ("conv_channels", "hidden"):
        if min(getattr(network, key)) < 1:
            raise PopcodeError(f"network.{key} widths must be at least 1, got {list(getattr(network, key))}")
    for key in ("conv_kernel", "squeeze_channels"):
        if getattr(network, key) < 1:
            raise PopcodeError(f"network.{key} must be at least 1, got {getattr(network, key)}")
    if max(*network.conv_channels, network.squeeze_channels) > MAX_CONV_CHANNELS:
        raise PopcodeError(f"network.conv_channels and squeeze_channels must be at most {MAX_CONV_CHANNELS} wide "
                           f"(each holds a crop-sized map per channel), got {list(network.conv_channels)}, "
                           f"{network.squeeze_channels}")


def parse_override(text: str) -> tuple[str, str, Any]:
    """``section.key=value`` -> (section, key, value); the value is read as TOML, else as a string."""
    path, sep, raw = text.partition("=")
    section, dot, key = path.strip().partition(".")
    if not sep or not dot or not key:
        raise PopcodeError(f"an override is section.key=value (e.g. train.lr=1e-3), got {text!r}")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return section, key, value


def _absolute(value: Any, base: Path) -> Any:
    """A path setting (a string or a list of them) made absolute against ``base``; anything else as it is."""
    if isinstance(value, str):
        return os.path.normpath(base / value) if value else value
    if isinstance(value, list):
        return [_absolute(item, base) for item in value]
    return value


def load_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> Config:
    """Read a TOML config (or the defaults when ``path`` is None) and apply overrides.

    Relative paths (:data:`PATH_SETTINGS`) in the file are relative to the file's folder, those of an override
    to the current folder; both are stored absolute, so export and evaluate find the data from anywhere.
    """
    data: dict[str, dict[str, Any]] = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise PopcodeError(f"config file not found: {path}")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as error:
            raise PopcodeError(f"{path} is not valid TOML: {error}") from error
        for section, key in PATH_SETTINGS:
            table = data.get(section)
            if isinstance(table, dict) and key in table:
                table[key] = _absolute(table[key], path.parent.absolute())
    for text in overrides:
        section, key, value = parse_override(text)
        table = data.setdefault(section, {})
        if not isinstance(table, dict):
            raise PopcodeError(f"config section [{section}] must be a table")
        table[key] = _absolute(value, Path.cwd()) if (section, key) in PATH_SETTINGS else value
    return Config.from_dict(data)
