"""What a ``popcode run``'s results depend on, as one fingerprint: a resume with any of it changed is refused.

The models' bytes (their external weights too), the detections' bytes, the
split's images and annotations, and the options that change a line or what is
drawn. The partial results file (:mod:`.run_results`) carries it in its first
line and in every image's checksum.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from collections.abc import Mapping
from itertools import islice
from pathlib import Path

from ..base.errors import PopcodeError
from ..bop.split import SplitImage
from .run_results import ImageKey

MAX_WEIGHT_FILES = 1000  # files beside a model looked at for its external weights


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (a resumed run must use the same models and detections); a FIFO or a device, whose
    read would never end, is refused."""
    if not path.is_file():
        raise PopcodeError(f"{path} is not a regular file (a FIFO or a device, say); replace it with a file")
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def model_digest(path: Path) -> str:
    """SHA-256 of a model and of the weights it keeps in other files (ONNX external data): the files in its folder,
    two levels down, whose relative path the model names (a location is stored as plain text in the model)."""
    data = path.read_bytes()
    digest = hashlib.sha256(data)
    folder = path.resolve().parent
    nearby = (found for pattern in ("*", "*/*") for found in folder.glob(pattern))
    candidates = sorted(found for found in islice(nearby, MAX_WEIGHT_FILES) if found.is_file())
    for candidate in candidates:
        name = candidate.relative_to(folder).as_posix()
        if candidate != path.resolve() and name.encode() in data:
            digest.update(f"\n{name}\n{file_digest(candidate)}".encode())
    return digest.hexdigest()


def split_digest(images: Mapping[ImageKey, SplitImage], depth: bool = False) -> str:
    """SHA-256 of what a split gives a run: each image's file name, size and modification time (``depth``: its depth
    image's too), and every scene's annotation files (cameras, boxes) by content. Cheap (one stat per image), and
    another split or an image changed in place, even to the same size, is told apart (a copy that keeps the times,
    ``cp -p`` or ``rsync -a``, still resumes)."""
    digest = hashlib.sha256()
    for key in sorted(images):
        paths = [images[key].path] + ([images[key].depth_path] if depth and images[key].depth_path else [])
        for path in paths:
            status = path.stat()
            digest.update(f"{key} {path.name} {status.st_size} {status.st_mtime_ns}\n".encode())
    for scene in sorted({images[key].path.parent.parent for key in images}):
        for annotation in sorted(scene.glob("*.json")):
            digest.update(f"{scene.name}/{annotation.name} {file_digest(annotation)}\n".encode())
    return digest.hexdigest()


def _detections_source(args: argparse.Namespace) -> object:
    """Where the boxes come from: a detections file's bytes, a detector's with its thresholds, or the split's own."""
    if args.detections:
        return file_digest(args.detections)
    if args.detector:
        return {"detector": model_digest(args.detector), "score_threshold": args.score_threshold,
                "nms_iou": args.nms_iou, "max_detections": args.max_detections}
    return {"gt_boxes": args.box_kind, "min_visib_fract": args.min_visib_fract}


def run_fingerprint(args: argparse.Namespace, images: Mapping[ImageKey, SplitImage]) -> str:
    """The fingerprint of a ``popcode run`` command line (``args``) over a split's ``images``."""
    parts = {"models": [model_digest(path) for path in args.models], "decoder": args.decoder,
             "providers": args.provider, "max_images": args.max_images, "split": split_digest(images, args.depth),
             "depth": args.depth, "refine": args.refine,
             "draw": None if args.draw is None else os.path.realpath(args.draw),
             "detections": _detections_source(args)}
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:32]
