"""The optional extra ``pip install ./runtime[ros]``: rosbags, imported only by the commands that read or write
ROS 2 bags, so that the core runtime stays numpy + onnxruntime + OpenCV (docs/architecture.md)."""

from __future__ import annotations

import importlib
from types import ModuleType

from ..base.errors import PopcodeError

INSTALL_HINT = "pip install ./runtime[ros] (it adds rosbags)"


def rosbags(module: str) -> ModuleType:
    """``rosbags.<module>`` (``rosbag2``, ``typesys``), or one line saying how to install it."""
    try:
        return importlib.import_module(f"rosbags.{module}")
    except ImportError as error:
        raise PopcodeError(f"reading and writing ROS 2 bags needs rosbags: {INSTALL_HINT}") from error
