"""The mutations :mod:`tools.fuzz_run` applies to what ``popcode run`` reads: the detections JSON, a BOP split's
JSON files, images and folder names, the ``<out>.partial`` of an interrupted run, and the options.

Each mutation changes a :class:`Call` (its working copy of the split on disk, its detections and partial file in
memory, its options) and returns a line saying what it did, so that a case can be read and replayed. A mutation
that can change which rows a correct run writes says so (``Call.changes_rows``); the others must leave a
successful run's rows exactly those of the unchanged inputs.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

OVERSIZE_BYTES = (1 << 26) + 1  # one byte over the runtime's JSON limit; written sparse, so it costs nothing
DETECTION_FIELDS = ("scene_id", "image_id", "category_id", "bbox", "score", "time")
HOSTILE_VALUES: tuple[Any, ...] = ("1", "", "٧", "0x1", "NaN", 1.7, -1, 0, 1, -0.0, 2 ** 63, 10 ** 18, 1e308, -1e308,
                                   5e-324, True, False, None, [], {}, [1], [[1]], {"a": 1}, [1, 2, 3, 4, 5])
# JSON texts Python's ``json.dumps`` never writes: non-standard constants, overflowing and very long numbers, nesting
HOSTILE_TOKENS = ("NaN", "Infinity", "-Infinity", "1e400", "-1e400", "1" * 400, "9" * 19, "-" + "9" * 30, "1E2",
                  "0.0000000", "-0", "[" * 100_000 + "]" * 100_000, "[" * 2000 + "]" * 2000)
HOSTILE_KEYS = ("abc", "1.0", " 0", "0 ", "+0", "٠", "00", "-1", "", "1e2", "9" * 25, "0x1", "0\n")
HOSTILE_NAMES = ("1", "0000001", "٠٠٠٠٠١", " 000001", "000001 ", "+1", "-1", "1.0", "0x1", "00000a", "9" * 30)
BOXES_OUTSIDE = ([500.0, 500.0, 20.0, 20.0], [-100.0, -100.0, 10.0, 10.0], [0.0, 0.0, 1e9, 1e9], [0, 0, 1e-9, 1e-9],
                 [150.0, 110.0, 40.0, 40.0], [-1e300, 0.0, 10.0, 10.0], [0.5, 0.5, 0.5, 0.5])
SCORES = (-3, 5, 1.0000001, -1e-9, 0, 1, 5e-324, 100)
MAX_IMAGES = ("0", "-1", "1", "2", "5", "6", "7", str(2 ** 63), str(10 ** 30), "abc", "1.5", "", "0x10", " 3", "٣")
MISSING = object()  # a file that the call does not write


def pick(rng: np.random.Generator, options: Sequence[Any]) -> Any:
    """One of ``options`` (``rng.choice`` would make an array of them, which mixed types cannot be)."""
    return options[int(rng.integers(len(options)))]


class Raw:
    """A JSON text written as it is (``NaN``, ``1e400``, 400 digits, deep nesting), where ``json.dumps`` cannot."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return f"Raw({self.text[:12]}{'...' if len(self.text) > 12 else ''})"


def dump_json(value: Any) -> bytes:
    """``value`` as JSON, with each :class:`Raw` in it written as its text."""
    raws: list[str] = []

    def placeholder(raw: Any) -> str:
        if not isinstance(raw, Raw):
            raise TypeError(f"cannot write {type(raw).__name__}")
        raws.append(raw.text)
        return f"@@raw{len(raws) - 1}@@"

    text = json.dumps(value, default=placeholder, ensure_ascii=False)
    text = re.sub(r'"@@raw(\d+)@@"', lambda found: raws[int(found.group(1))], text)
    return text.encode()


@dataclass
class Call:
    """One case's inputs as the mutations leave them: a working copy of the split in ``folder``, the detections
    (a JSON value, raw bytes, or :data:`MISSING`), the ``.partial`` bytes (None: no file), models and options."""

    folder: Path
    split: Path
    mode: str  # "detections" or "gt" (--gt-boxes)
    detections: Any
    partial: bytes | None
    other_partial: bytes  # a partial file of a run with other inputs, for its header and its blocks
    models: list[str]
    options: dict[str, str | None] = field(default_factory=dict)  # option -> value (None: a flag)
    out: str = ""
    changes_rows: bool = False
    forged: bool = False  # a partial file's row changed with its checksum recomputed: in range, it is undetectable
    done: list[str] = field(default_factory=list)  # what each mutation did

    @property
    def tree(self) -> Path:
        """The call's copy of the split, which the mutations change (``split`` is what ``--split`` names)."""
        return self.folder / "split"

    @property
    def detections_path(self) -> Path:
        return self.folder / "detections.json"

    def argv(self) -> list[str]:
        source = ["--detections", str(self.detections_path)] if self.mode == "detections" else ["--gt-boxes"]
        options = [part for key, value in self.options.items() for part in ([key] if value is None else [key, value])]
        return ["run", *self.models, "--split", str(self.split), *source, "--out", self.out, *options]


Mutation = Callable[[Call, np.random.Generator], str]


def _hostile_value(rng: np.random.Generator) -> Any:
    return Raw(pick(rng, HOSTILE_TOKENS)) if rng.random() < 0.35 else pick(rng, HOSTILE_VALUES)


def _paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every place in a JSON value (keys of objects, indices of lists), parents before children."""
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    found = []
    for key, child in children:
        found.append((*prefix, key))
        found += _paths(child, (*prefix, key))
    return found


def _parent(value: Any, path: tuple[Any, ...]) -> Any:
    for key in path[:-1]:
        value = value[key]
    return value


def mutate_json_value(value: Any, rng: np.random.Generator) -> tuple[Any, str]:
    """One random change inside a JSON value: a place set to a hostile value, a key renamed, doubled (another
    spelling of one id) or removed."""
    paths = _paths(value)
    if not paths:
        return _hostile_value(rng), "the whole value replaced"
    path = pick(rng, paths)
    parent, key = _parent(value, path), path[-1]
    kind = rng.integers(4)
    if kind <= 1:
        parent[key] = _hostile_value(rng)
        return value, f"{list(path)} = {parent[key]!r:.60}"
    if kind == 2 and isinstance(parent, dict):
        new_key = pick(rng, HOSTILE_KEYS + tuple(parent))  # a key named twice collapses to one
        parent[new_key] = parent.pop(key)
        return value, f"key {list(path)} renamed {new_key!r:.30}"
    if kind == 3 and isinstance(parent, dict) and str(key).isdigit():  # "3" and "03": two keys of one id
        parent["0" + key] = copy.deepcopy(parent[key])
        return value, f"key {list(path)} also as {'0' + key!r}"
    del parent[key]
    return value, f"{list(path)} removed"


def mutate_bytes(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """One change of a file's bytes: torn, garbage, invalid UTF-8, another encoding, empty, deeply nested."""
    at = int(rng.integers(len(data) + 1))
    kind = rng.integers(9)
    if kind == 0:
        return data[:at], f"torn at byte {at} of {len(data)}"
    if kind == 1:
        garbage = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        return data[:at] + garbage + data[at:], f"{len(garbage)} random bytes at {at}"
    if kind == 2:
        return data[:at] + b"\xff\xfe" + data[at:], f"invalid UTF-8 at {at}"
    if kind == 3:
        return b"\xef\xbb\xbf" + data, "a UTF-8 byte-order mark"
    if kind == 4:
        return data.decode("utf-8", "replace").encode("utf-16"), "UTF-16"
    if kind == 5:
        return b"", "empty"
    if kind == 6:
        return b"[" * 100_000 + b"]" * 100_000, "100 000 levels of nesting"
    if kind == 7:
        return data.replace(b"\n", b"\r\n") + b"\n\n  \t", "CRLF and trailing white space"
    return data[:at] + b"\x00" + data[at:], f"a NUL byte at {at}"


def real(path: str | os.PathLike) -> Path:
    """The path with its symbolic links followed (``Path.resolve`` raises on a loop, which the fuzz makes)."""
    return Path(os.path.realpath(path))


def regular(path: Path) -> bool:
    """Whether the fuzz may read ``path``: a regular file, not a link (to a FIFO, say, whose read never ends)."""
    return path.is_file() and not path.is_symlink()


def file_in_place(path: Path, rng: np.random.Generator) -> str:
    """A file replaced by what is no readable file: nothing, a folder, a sparse file over the JSON limit, a link
    to itself or to a device, a FIFO (reading one waits for a writer forever)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    path.unlink(missing_ok=True)
    kind = rng.integers(6)
    if kind == 0:
        return "missing"
    if kind == 1:
        path.mkdir()
        return "a folder"
    if kind == 2:
        with path.open("wb") as handle:
            handle.truncate(OVERSIZE_BYTES)
        return f"{OVERSIZE_BYTES} bytes (sparse)"
    if kind == 3:
        path.symlink_to(path.name)
        return "a symbolic link to itself"
    if kind == 4:
        path.symlink_to("/dev/null")  # not /dev/zero: a reader without bounds would eat the machine's memory
        return "a symbolic link to /dev/null"
    os.mkfifo(path)
    return "a FIFO"


# --- detections ---------------------------------------------------------------------------------------------------

def _entries(call: Call) -> list[Any] | None:
    return call.detections if isinstance(call.detections, list) and call.detections else None


def detection_value(call: Call, rng: np.random.Generator) -> str:
    if (entries := _entries(call)) is None:
        return "nothing to change"
    index = int(rng.integers(len(entries)))
    if not isinstance(entries[index], dict) or rng.random() < 0.3:
        entries[index], what = mutate_json_value(entries[index], rng)
        return f"detection {index}: {what}"
    key = pick(rng, DETECTION_FIELDS)
    entries[index][key] = _hostile_value(rng)
    return f"detection {index}: {key} = {entries[index][key]!r:.60}"


def detection_fields(call: Call, rng: np.random.Generator) -> str:
    if (entries := _entries(call)) is None or not isinstance(entries[index := int(rng.integers(len(entries)))], dict):
        return "nothing to change"
    if rng.random() < 0.5:
        key = pick(rng, DETECTION_FIELDS)
        entries[index].pop(key, None)
        call.changes_rows = True
        return f"detection {index}: {key} removed"
    entries[index][pick(rng, ("extra", "bbox_visib", "segmentation", "Score"))] = _hostile_value(rng)
    return f"detection {index}: an extra key"


def detection_box(call: Call, rng: np.random.Generator) -> str:
    if (entries := _entries(call)) is None or not isinstance(entries[index := int(rng.integers(len(entries)))], dict):
        return "nothing to change"
    entries[index]["bbox"] = list(pick(rng, BOXES_OUTSIDE))
    return f"detection {index}: bbox {entries[index]['bbox']}"


def detection_score(call: Call, rng: np.random.Generator) -> str:
    if (entries := _entries(call)) is None or not isinstance(entries[index := int(rng.integers(len(entries)))], dict):
        return "nothing to change"
    entries[index]["score"] = pick(rng, SCORES)
    return f"detection {index}: score {entries[index]['score']!r}"


def detection_target(call: Call, rng: np.random.Generator) -> str:
    """A detection of an object no model knows (skipped), or of an image the split lacks (refused)."""
    if (entries := _entries(call)) is None or not isinstance(entries[index := int(rng.integers(len(entries)))], dict):
        return "nothing to change"
    key, value = pick(rng, (("category_id", 0), ("category_id", 7), ("category_id", 99), ("category_id", 10 ** 9),
                            ("image_id", 1), ("image_id", 10 ** 12), ("scene_id", 0), ("scene_id", 99)))
    entries[index][key] = value
    return f"detection {index}: {key} {value}"


def detection_copies(call: Call, rng: np.random.Generator) -> str:
    if (entries := _entries(call)) is None:
        return "nothing to change"
    index, copies = int(rng.integers(len(entries))), int(pick(rng, (1, 2, 30, 300)))
    entries[index + 1:index + 1] = [copy.deepcopy(entries[index]) for _ in range(copies)]
    order = "shuffled" if rng.random() < 0.3 else "in order"
    if order == "shuffled":
        entries[:] = [entries[i] for i in rng.permutation(len(entries))]
    return f"detection {index} {copies} more times, {order}"


def detections_whole(call: Call, rng: np.random.Generator) -> str:
    """The whole file: another JSON value, hostile bytes, or no readable file at all."""
    if call.detections is MISSING:
        return "no file to change"
    kind = rng.integers(3)
    if kind == 0:
        inner = [] if isinstance(call.detections, bytes) else call.detections
        call.detections = pick(rng, ([], {}, {"detections": inner}, [inner], "[]", 5, None,
                                     [[1, 0, 1, [0, 0, 9, 9], 0.5, 0.1]]))
        return f"the file holds {dump_json(call.detections)[:40]!r}"
    if kind == 1:
        data = call.detections if isinstance(call.detections, bytes) else dump_json(call.detections)
        call.detections, what = mutate_bytes(data, rng)
        return f"bytes: {what}"
    call.detections_path.unlink(missing_ok=True)
    what = file_in_place(call.detections_path, rng)
    call.detections = MISSING
    return f"the file: {what}"


# --- the split's JSON files -----------------------------------------------------------------------------------------

def _scene(call: Call, rng: np.random.Generator) -> Path | None:
    scenes = sorted(path for path in call.tree.iterdir() if path.is_dir() and (path / "scene_gt.json").exists())
    return pick(rng, scenes) if scenes else None


def split_json(call: Call, rng: np.random.Generator) -> str:
    """One of a scene's ``scene_gt.json``, ``scene_gt_info.json``, ``scene_camera.json``: a value, a key, bytes."""
    if (scene := _scene(call, rng)) is None:
        return "no scene to change"
    path = scene / pick(rng, ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"))
    where = f"{scene.name}/{path.name}"
    if not regular(path):
        return f"{where} is no file to change"
    kind = rng.random()
    if kind < 0.6:
        try:
            value = json.loads(path.read_bytes())
        except ValueError:
            return f"{where} is no JSON to change"
        value, what = mutate_json_value(value, rng)
        path.write_bytes(dump_json(value))
        return f"{where}: {what}"
    if kind < 0.85:
        data, what = mutate_bytes(path.read_bytes(), rng)
        path.write_bytes(data)
        return f"{where} bytes: {what}"
    return f"{where}: {file_in_place(path, rng)}"


def _edit_entries(path: Path, edit: Callable[[dict[str, Any]], str]) -> str:
    """``edit`` applied to the first entry of each image of a split JSON file that is still readable."""
    if not regular(path):
        return f"{path.parent.name}/{path.name} is no file to change"
    try:
        value = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return f"{path.parent.name}/{path.name} is no JSON to change"
    what = ""
    for entries in value.values() if isinstance(value, dict) else ():
        entry = entries[0] if isinstance(entries, list) and entries else entries
        if isinstance(entry, dict):
            what = edit(entry)
    path.write_bytes(dump_json(value))
    return f"{path.parent.name}/{path.name}: {what or 'nothing to change'}"


def camera(call: Call, rng: np.random.Generator) -> str:
    if (scene := _scene(call, rng)) is None:
        return "no scene to change"
    K = pick(rng, ([0.0] * 9, [-192.0, 0, 79.5, 0, 192, 59.5, 0, 0, 1], [192.0, 0, 79.5, 0, 192, 59.5, 0, 0],
                   [[192.0, 0, 79.5], [0, 192, 59.5], [0, 0, 1]], [192.0, 0, 79.5, 0, 192, 59.5, 0, 0, 2],
                   [1e300, 0, 79.5, 0, 1e300, 59.5, 0, 0, 1], [1e-300, 0, 79.5, 0, 1e-300, 59.5, 0, 0, 1],
                   [192.0, 0, 1e9, 0, 192, -1e9, 0, 0, 1], "192 0 79.5 0 192 59.5 0 0 1"))

    def edit(entry: dict[str, Any]) -> str:
        entry["cam_K"] = K
        return f"cam_K {K!r:.70}"
    return _edit_entries(scene / "scene_camera.json", edit)


def ground_truth(call: Call, rng: np.random.Generator) -> str:
    """An instance's object id, visibility or box changed, or one instance more in only one of the two files."""
    if (scene := _scene(call, rng)) is None:
        return "no scene to change"
    kind = rng.integers(4)
    if kind == 0:
        obj_id = pick(rng, (1, 3, 6, 0, 99, -1, 2 ** 40))

        def edit(entry: dict[str, Any]) -> str:
            entry["obj_id"] = obj_id
            return f"obj_id {obj_id}"
        return _edit_entries(scene / "scene_gt.json", edit)
    if kind == 1:
        visib = pick(rng, (-1, 2, 0.05, 0.1, 0, Raw("NaN"), "0.5", 1e-300))

        def edit(entry: dict[str, Any]) -> str:
            entry["visib_fract"] = visib
            return f"visib_fract {visib!r}"
        return _edit_entries(scene / "scene_gt_info.json", edit)
    if kind == 2:
        box = list(pick(rng, BOXES_OUTSIDE + ([10, 10, 0, 5], [10, 10, -5, 5])))

        def edit(entry: dict[str, Any]) -> str:
            entry[pick(rng, ("bbox_obj", "bbox_visib"))] = box
            return f"box {box}"
        return _edit_entries(scene / "scene_gt_info.json", edit)
    path = scene / pick(rng, ("scene_gt.json", "scene_gt_info.json"))
    try:
        value = json.loads(path.read_bytes() if regular(path) else b"")
        entries = next(iter(value.values()))
        entries.append(json.loads(json.dumps(entries[0])))
    except (OSError, ValueError, AttributeError, StopIteration, IndexError, TypeError):
        return f"{path.parent.name}/{path.name} is no list to extend"
    path.write_bytes(dump_json(value))
    return f"{path.parent.name}/{path.name}: one instance more"


# --- images and folder names ----------------------------------------------------------------------------------------

def _image_files(call: Call) -> list[Path]:
    return sorted(path for scene in call.tree.iterdir() if scene.is_dir() for name in ("gray", "rgb")
                  if (scene / name).is_dir() for path in (scene / name).iterdir())


def _png(image: np.ndarray, compression: int = 3) -> bytes:
    return cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, compression])[1].tobytes()


def image_file(call: Call, rng: np.random.Generator) -> str:
    """One image missing, torn, garbage, of another size, depth or format, or a header that claims 10^10 pixels."""
    files = [path for path in _image_files(call) if regular(path)]
    if not files:
        return "no image to change"
    path = pick(rng, files)
    where, data = f"{path.parent.parent.name}/{path.parent.name}/{path.name}", path.read_bytes()
    kind = rng.integers(10)
    if kind == 0:
        path.unlink()
        return f"{where} removed"
    if kind == 1:
        at = int(rng.integers(len(data)))
        path.write_bytes(data[:at])
        return f"{where} torn at byte {at}"
    if kind == 2:
        path.write_bytes(rng.integers(0, 256, int(rng.integers(0, 3000)), dtype=np.uint8).tobytes())
        return f"{where} random bytes"
    if kind == 3:  # a valid PNG of another size, depth or channel count
        height, width = pick(rng, ((1, 1), (3, 500), (240, 320), (160, 120), (2, 2000), (120, 160)))
        channels, dtype = pick(rng, ((1, np.uint8), (3, np.uint8), (4, np.uint8), (1, np.uint16), (3, np.uint16)))
        image = rng.integers(0, np.iinfo(dtype).max, (height, width, channels), dtype=dtype)
        path.write_bytes(_png(image))
        return f"{where} {width}x{height}, {channels} channel(s) of {np.dtype(dtype).name}"
    if kind == 4:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            return f"{where} is no image to transpose"
        path.write_bytes(_png(np.ascontiguousarray(image.swapaxes(0, 1))))
        return f"{where} width and height swapped"
    if kind == 5:
        size = (100_000).to_bytes(4, "big") * 2
        path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + size + b"\x08\x00\x00\x00\x00" + b"\x00" * 64)
        return f"{where} a PNG header of 100000x100000 pixels"
    if kind == 6:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        path.write_bytes(cv2.imencode(".jpg", image)[1].tobytes() if image is not None else data)
        return f"{where} JPEG bytes under a .png name"
    if kind == 7:
        twin = path.with_suffix(pick(rng, (".jpg", ".tif", ".png.bak", "")))
        shutil.copyfile(path, twin)
        return f"{where} copied to {twin.name}"
    if kind == 8:  # what a cheap fingerprint (names and sizes) misses: padding after IEND keeps the file's size
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        other = _png(np.ascontiguousarray(image[:, ::-1]), 9) if image is not None else data  # mirrored
        if image is None or len(other) > len(data):
            return f"{where} is no image to change in place"
        path.write_bytes(other + b"\0" * (len(data) - len(other)))
        return f"{where} other pixels, the same file size"
    return f"{where}: {file_in_place(path, rng)}"


def names(call: Call, rng: np.random.Generator) -> str:
    """A scene folder, image folder or image renamed (to its id spelled otherwise, or to what is no id), doubled,
    or a stray folder or file beside them."""
    scenes = sorted(path for path in call.tree.iterdir() if path.is_dir())
    files = [path for path in _image_files(call) if path.is_file()]
    kind = rng.integers(6)
    if kind == 0 and scenes:
        scene, name = pick(rng, scenes), pick(rng, HOSTILE_NAMES)
        if (call.tree / name).exists():
            return f"scene {scene.name}: {name!r} exists"
        scene.rename(call.tree / name)
        return f"scene {scene.name} renamed {name!r}"
    if kind == 1 and scenes:
        scene = pick(rng, scenes)
        twin = call.tree / (str(int(scene.name)) if scene.name.isdigit() and scene.name.isascii() else "000001")
        if twin.exists():
            return f"scene {scene.name}: {twin.name} exists"
        with contextlib.suppress(shutil.Error, OSError):  # a FIFO in it is left out (copying it raises)
            shutil.copytree(scene, twin, symlinks=True)
        return f"scene {scene.name} copied to {twin.name}"
    if kind == 2 and scenes:
        scene = pick(rng, scenes)
        folder = next((scene / name for name in ("gray", "rgb") if (scene / name).is_dir()), None)
        if folder is None:
            return f"scene {scene.name} has no image folder"
        target = pick(rng, ("rgb", "grey", "gray_", "depth"))
        if rng.random() < 0.3:
            (scene / "rgb").mkdir(exist_ok=True)
            return f"scene {scene.name}: an empty rgb/ beside {folder.name}/"
        if (scene / target).exists():
            shutil.rmtree(scene / target)
        folder.rename(scene / target)
        return f"scene {scene.name}: {folder.name}/ renamed {target}/"
    if kind == 3 and files:
        path = pick(rng, files)
        name = pick(rng, ("0.png", "abc.png", "٠.png", "000000", "000000.PNG", ".000000.png", "-0.png", "0_0.png",
                          "00000000000000000000000.png"))
        if (path.parent / name).exists():
            return f"{path.name}: {name} exists"
        path.rename(path.parent / name)
        return f"{path.parent.parent.name}/{path.parent.name}/{path.name} renamed {name!r}"
    if kind == 4:
        name = pick(rng, ("000099", "000007", "notes", "000099.json"))
        target = call.tree / name
        if target.exists():
            return f"{name} exists"
        if rng.random() < 0.5:
            target.mkdir()
        else:
            target.write_bytes(b"x")
        return f"a stray {'folder' if target.is_dir() else 'file'} {name}"
    for scene in scenes:
        shutil.rmtree(scene)
    return "every scene folder removed"


# --- the partial file of an interrupted run -----------------------------------------------------------------------

def _checksum(lines: list[str], header: str) -> str:
    """What ``popcode run`` closes an image's lines with (SHA-256 of the run's fingerprint, which its header holds,
    and the lines; 16 hex digits): forging it needs no secret."""
    return hashlib.sha256("\n".join([header.removeprefix("#popcode-run "), *lines]).encode()).hexdigest()[:16]


def _blocks(lines: list[str]) -> list[tuple[int, int]]:
    """(first, last) line index of each image's lines and its closing ``#done`` mark."""
    blocks, start = [], 1
    for index, line in enumerate(lines):
        if index and line.startswith("#done "):
            blocks.append((start, index))
            start = index + 1
    return blocks


def partial_lines(call: Call, rng: np.random.Generator) -> str:
    """Lines of the partial file torn, edited, duplicated, swapped, dropped, garbage, blank, or its header another
    run's."""
    if call.partial is None:
        return "no partial file"
    lines = call.partial.decode("utf-8", "replace").split("\n")
    lines += [""] * (2 - len(lines))
    body = list(range(1, max(2, len(lines) - 1)))  # the last line is empty after the final newline
    index = pick(rng, body)
    kind = rng.integers(9)
    if kind == 0:
        line = lines[index]
        at = int(rng.integers(len(line) + 1))
        lines[index] = line[:at] + pick(rng, list("0123456789.-,e #x\t")) + line[at + 1:]
        what = f"line {index} edited at {at}"
    elif kind == 1:
        lines.insert(index, pick(rng, ("not,a,row", "#done 1 0 0123456789abcdef", ",,,,,,", "#", "1,0,1,0.5,1 0 0 0 1 "
                                       "0 0 0 1,0 0 100,0.1", "x" * 100_000)))
        what = f"a garbage line at {index}"
    elif kind == 2:
        lines.insert(index, lines[index])
        what = f"line {index} twice"
    elif kind == 3:
        blocks = _blocks(lines)
        if blocks:
            first, last = pick(rng, blocks)
            lines += lines[first:last + 1]
        what = "an image's block twice"
    elif kind == 4:
        other = pick(rng, body)
        lines[index], lines[other] = lines[other], lines[index]
        what = f"lines {index} and {other} swapped"
    elif kind == 5:
        del lines[index]
        what = f"line {index} removed"
    elif kind == 6:
        header = call.other_partial.decode().split("\n")[0]
        lines[0] = pick(rng, (header, "#popcode-run " + "0" * 32, "#popcode-run ", "", lines[0] + " "))
        what = f"header {lines[0][:24]!r}..."
    elif kind == 7:
        lines[index:index] = [""] * int(rng.integers(1, 4))
        what = f"blank lines at {index}"
    else:
        other = call.other_partial.decode().split("\n")
        blocks = _blocks(other)
        if blocks:
            first, last = pick(rng, blocks)
            lines[index:index] = other[first:last + 1]
        what = "another run's image block inserted"
    call.partial = "\n".join(lines).encode()
    return f"partial: {what}"


def partial_forged(call: Call, rng: np.random.Generator) -> str:
    """A row of a closed image changed, its checksum recomputed, as someone who read the format would."""
    if call.partial is None:
        return "no partial file"
    lines = call.partial.decode("utf-8", "replace").split("\n")
    blocks = _blocks(lines)
    if not blocks:
        return "partial: no closed image to forge"
    first, last = pick(rng, blocks)
    fields = lines[first].split(",")
    if len(fields) != 7:
        return "partial: no row to forge"
    column, value = pick(rng, ((3, "5"), (3, "-1"), (3, "0.5"), (3, "nan"), (4, "1 0 0 0 1 0 0 0 2"),
                               (4, "1 0 0 0 1 0 0 0 1"), (5, "1e300 0 0"), (5, "0 0 0"), (1, "77"), (2, "99"),
                               (0, "0"), (6, "-5"), (6, "1e308"), (2, "٣")))
    fields[column] = value
    lines[first] = ",".join(fields)
    lines[last] = " ".join(lines[last].split(" ")[:3] + [_checksum(lines[first:last], lines[0])])
    call.partial = "\n".join(lines).encode()
    call.changes_rows = call.forged = True
    return f"partial: row {first} field {column} = {value!r}, checksum recomputed"


def partial_file(call: Call, rng: np.random.Generator) -> str:
    """The partial file as a whole: hostile bytes, header only, no readable file (:func:`file_in_place`), or a
    finished results file, a stale lock or no readable lock file beside it."""
    if call.partial is None:
        return "no partial file"
    kind = rng.integers(6)
    if kind == 0:
        call.partial, what = mutate_bytes(call.partial, rng)
        return f"partial bytes: {what}"
    if kind == 1:
        call.partial = call.partial.split(b"\n")[0] + b"\n"
        return "partial: its header only"
    out = Path(call.out)
    if not out.parent.is_dir() or not real(out).is_relative_to(real(call.folder)) or len(out.name) > 240:
        return "partial: no place for a file beside --out"
    if kind == 2:
        call.partial = None
        return f"partial: {file_in_place(out.with_name(out.name + '.partial'), rng)}"
    if kind == 3:
        out.write_text("scene_id,im_id,obj_id,score,R,t,time\n")
        return "a finished results file beside the partial"
    if kind == 4:
        out.with_name(out.name + ".lock").write_text("")
        return "a stale lock file (no process holds it)"
    return f"the lock file: {file_in_place(out.with_name(out.name + '.lock'), rng)}"


# --- options ------------------------------------------------------------------------------------------------------

def options(call: Call, rng: np.random.Generator) -> str:
    kind = rng.integers(8)
    if kind == 0:
        call.options["--max-images"] = pick(rng, MAX_IMAGES)
        call.changes_rows = True
        return f"--max-images {call.options['--max-images']!r}"
    if kind == 1:
        out, name = Path(call.out), pick(rng, ("folder", "long", "no-folder", "slash", "input", "split"))
        call.out = {"folder": str(call.folder), "long": str(out.with_name("r" * int(pick(rng, (196, 197, 250, 300)))
                                                                          + ".csv")),
                    "no-folder": str(out.parent / "missing" / out.name), "slash": str(out.with_suffix("")) + "/",
                    "input": str(call.detections_path if call.mode == "detections" else call.tree / "000001"
                                 / "scene_gt.json"),
                    "split": str(call.split)}[name]
        return f"--out {name}"
    if kind == 2:
        call.split = pick(rng, (call.folder / "missing", call.detections_path, call.tree / "000001"))
        return f"--split {call.split.name}"
    if kind == 3 and call.mode == "gt":
        call.options["--min-visib-fract"] = pick(rng, ("nan", "-1", "2", "inf", "0", "1", "1e-300"))
        call.changes_rows = True
        return f"--min-visib-fract {call.options['--min-visib-fract']}"
    if kind == 3:
        call.options["--box-kind"] = "bbox_visib"  # accepted and unused without --gt-boxes
        return "--box-kind bbox_visib"
    if kind == 4:
        call.options["--decoder"] = "refined"
        call.changes_rows = True
        return "--decoder refined"
    if kind == 5:
        choice = int(rng.integers(3))
        call.models = [call.models[::-1], call.models[:1], [call.models[0], call.models[0]]][choice]
        call.changes_rows = True
        return ["models swapped", "one model", "one model twice"][choice]
    if kind == 6:
        draw = pick(rng, ("drawn", "missing", "detections.json"))
        (call.folder / "drawn").mkdir(exist_ok=True)
        call.options["--draw"] = str(call.folder / draw)
        return f"--draw {draw}"
    call.options.pop("--quiet", None)
    return "progress shown"


# group -> mutations; :mod:`tools.fuzz_run` draws a group, then one of its mutations
MUTATIONS: dict[str, tuple[Mutation, ...]] = {
    "detections": (detection_value, detection_fields, detection_box, detection_score, detection_target,
                   detection_copies, detections_whole),
    "split": (split_json, camera, ground_truth, image_file, names),
    "partial": (partial_lines, partial_forged, partial_file),
    "options": (options,),
}
NEUTRAL = {partial_lines, partial_file}  # a run they leave successful writes the same rows
SAY_SO = {detection_fields, partial_forged, options}  # they set ``Call.changes_rows`` themselves


def apply(mutation: Mutation, call: Call, rng: np.random.Generator) -> None:
    """Apply one mutation, note what it did and whether it may change the rows."""
    what = mutation(call, rng)
    call.done.append(f"{mutation.__name__}: {what}")
    if mutation not in NEUTRAL | SAY_SO:
        call.changes_rows = True


def write_inputs(call: Call, overwrite: bool = False) -> None:
    """The call's detections and partial file onto disk, as the mutations left them (a partial file already there
    is replaced only when ``overwrite``). A partial file goes only where the call's folder holds it."""
    if call.mode == "detections" and call.detections is not MISSING:
        data = call.detections if isinstance(call.detections, bytes) else dump_json(call.detections)
        call.detections_path.write_bytes(data)
    out = Path(call.out)
    partial = out.with_name(out.name + ".partial")
    if call.partial is None or len(partial.name) > 250 or not partial.parent.is_dir() or \
            not real(partial).is_relative_to(real(call.folder)):
        return
    if not partial.exists() or (overwrite and partial.is_file()):
        partial.write_bytes(call.partial)
