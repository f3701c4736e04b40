"""The optional extra ``pip install ./runtime[ros]``: rosbags (ROS 2 bags) and foxglove-sdk (Foxglove's MCAP
files), imported only by the commands that read or write them, so that the core runtime stays numpy + onnxruntime
+ OpenCV (docs/architecture.md)."""

from __future__ import annotations

import importlib
from types import ModuleType

from ..base.errors import PopcodeError

INSTALL_HINT = "pip install ./runtime[ros] (it adds rosbags and foxglove-sdk)"


def optional_module(name: str) -> ModuleType:
    """The module ``name`` of the extra (``rosbags.rosbag2``, ``foxglove``), or one line saying how to install it."""
    try:
        return importlib.import_module(name)
    except ImportError as error:
        raise PopcodeError(f"{name.split('.')[0]} is not installed: {INSTALL_HINT}") from error


def rosbags(module: str) -> ModuleType:
    """``rosbags.<module>`` (``rosbag2``, ``typesys``)."""
    return optional_module(f"rosbags.{module}")
