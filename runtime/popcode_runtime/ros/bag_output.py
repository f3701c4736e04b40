"""The bag ``popcode bag`` writes: a rosbag2 folder (MCAP or SQLite3) of ``Detection3DArray`` and ``PoseArray``,
written whole or not at all.

rosbags writes a folder, so the atomic write is the folder's: the bag is written, under its own name, inside a
temporary folder beside the target (``.<name>.<pid>-<host>.<random>.tmp``, as
:func:`~popcode_runtime.base.files.atomic_path` names its files), its files and folder synced, then renamed to
the target. An existing bag replaced with ``--overwrite`` is moved aside first and removed after the rename (for
that moment no bag is at the target); a failed or interrupted run removes its temporary folder and leaves the
target as it was.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..base.errors import PopcodeError, library_step
from ..base.files import MAX_NAME_BYTES, refuse_existing, refuse_inputs, sync_file, sync_folder, temporary_name
from ..inference.frame import FramePose
from .bag_input import CameraFrame
from .library import rosbags
from .messages import DETECTIONS_TYPE, POSES_TYPE, detection_array, pose_array, typestore

STORAGES = ("mcap", "sqlite3")
BAG_METADATA = "metadata.yaml"  # what every rosbag2 folder holds


def check_bag_output(out: Path, inputs: Sequence[Path], overwrite: bool) -> Path:
    """``out`` as a new bag folder: its parent writable, none of the inputs; an existing one replaced only with
    ``overwrite`` and only when it is a rosbag2 folder (never a file or another folder)."""
    refuse_inputs(out, "--out", inputs)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise PopcodeError(f"--out {out}: folder {parent} does not exist or is not writable")
    if len(out.name.encode()) > MAX_NAME_BYTES:
        raise PopcodeError(f"--out {out}: the name is longer than {MAX_NAME_BYTES} bytes")
    refuse_existing(out, "--out", overwrite)
    if out.exists() and not (out.is_dir() and not out.is_symlink() and (out / BAG_METADATA).is_file()):
        raise PopcodeError(f"--out {out} exists and is not a rosbag2 folder (no {BAG_METADATA}); --overwrite "
                           "replaces only a bag: choose another path")
    return out


class BagOutput:
    """The output bag, open while its frames are added; :meth:`finish` puts it in place."""

    def __init__(self, out: Path, storage: str, detections_topic: str, poses_topic: str,
                 objects: Mapping[int, Mapping[str, Any]]) -> None:
        rosbag2 = rosbags("rosbag2")
        self.out, self.objects = out, objects
        self.holder = temporary_name(out)  # the bag's files are named after its folder: out/out.mcap
        self.holder.mkdir()
        self.temporary = self.holder / out.name
        plugin = rosbag2.StoragePlugin.MCAP if storage == "mcap" else rosbag2.StoragePlugin.SQLITE3
        self.writer = rosbag2.Writer(self.temporary, version=rosbag2.Writer.VERSION_LATEST, storage_plugin=plugin)
        self.frames = 0
        try:
            with library_step(f"write bag {self.temporary}"):
                self.writer.open()
                self.detections = self.writer.add_connection(detections_topic, DETECTIONS_TYPE,
                                                             typestore=typestore())
                self.poses = self.writer.add_connection(poses_topic, POSES_TYPE, typestore=typestore())
        except BaseException:
            self.abort()
            raise

    def __enter__(self) -> BagOutput:
        return self

    def __exit__(self, kind: type | None, *exc_info: object) -> None:
        if kind is not None:
            self.abort()

    def add(self, frame: CameraFrame, poses: Sequence[FramePose]) -> None:
        """One frame's estimates, at the image's bag time, with its header (an empty array for a frame without
        parts: a listener learns the frame was looked at)."""
        store = typestore()
        with library_step(f"write bag {self.temporary}"):
            self.writer.write(self.detections, frame.time_ns,
                              store.serialize_cdr(detection_array(frame.header, poses, self.objects), DETECTIONS_TYPE))
            self.writer.write(self.poses, frame.time_ns,
                              store.serialize_cdr(pose_array(frame.header, poses), POSES_TYPE))
        self.frames += 1

    def finish(self) -> None:
        """Close the bag, sync it and rename it to ``out`` (a bag there already moved aside, then removed)."""
        with library_step(f"write bag {self.temporary}"):
            self.writer.close()
        for path in self.temporary.iterdir():
            sync_file(path)
        sync_folder(self.temporary)
        old = temporary_name(self.out) if self.out.exists() else None
        if old is not None:
            os.rename(self.out, old)
        os.rename(self.temporary, self.out)
        sync_folder(self.out.parent if str(self.out.parent) else Path("."))
        self.holder.rmdir()
        if old is not None:
            shutil.rmtree(old)

    def abort(self) -> None:
        """Remove the temporary folder; ``out`` keeps what it held."""
        shutil.rmtree(self.holder, ignore_errors=True)
