"""The frame path on the sample bin frame: the shipped detector's boxes however the file is read, and the
letterbox's pad.

    python -m bench.frame_path

1. Boxes of ``models/builtin-parts-detector.onnx`` on ``models/samples/bin.png`` (720 x 540, 8-bit) as stored
   (what ``popcode detect``, ``detect --split`` and ``run --detector`` hand the detector), as ``read_image`` gives
   it (float: ``predict --detector``, ``FramePoseEstimator``) and as its 16-bit copy.
2. The pad of the letterbox: four crops of the bin frame that keep the detector's scale (16:9 from the top and
   the bottom, 3:4 from the left and the right), padded to 4:3 with a grey value as the letterbox pads them:
   boxes whose centre lies in the pad (nothing is there), and the instances wholly inside a crop found with
   their object (IoU >= 0.5 with ``bbox_obj``).

3. The bin frame inside larger frames of 4:3, 16:9 and portrait aspect: how many of its parts are found when the
   detector sees them smaller.

Writes ``bench/results/frame-path.{json,md}``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from popcode_runtime import Detector, read_image
from popcode_runtime.geometry.crop import read_image_file
from popcode_runtime.model.detector_metadata import DETECTOR_INPUT_MEAN
from popcode_trainer.data.box_noise import box_intersection, box_iou
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import MODELS_DIR, RESULTS, SHIPPED_DETECTOR
from tools.report import machine, machine_line, write_results

DETECTOR = SHIPPED_DETECTOR
SAMPLE = MODELS_DIR / "samples" / "samples.json"
CROPS = {"16:9 top": (0, 0, 720, 405), "16:9 bottom": (0, 135, 720, 405), "3:4 left": (0, 0, 405, 540),
         "3:4 right": (315, 0, 405, 540)}  # x, y, width, height in the 720 x 540 frame
MATCH_IOU = 0.5
# The bin frame inside larger frames (columns, rows, where its corner lies), the rest grey 200: seen smaller by the
# detector. The 4:3 frame needs no pad and sees the bin at the 16:9 frame's scale: the letterbox's own cost.
LARGER = {"4:3, 960 x 720 (no pad)": (960, 720, 120, 90), "16:9, 960 x 540": (960, 540, 120, 0),
          "portrait, 720 x 960": (720, 960, 0, 210)}
FILL = 200


def _sample() -> tuple[Path, list[dict]]:
    """The bin frame's file and its instances."""
    sample = json.loads(SAMPLE.read_text())["bin"]
    return SAMPLE.parent / sample["image"], sample["instances"]


def readings(detector: Detector, path: Path) -> list[list]:
    """Per way of reading the file: the box count and the largest difference of a box edge from the stored file's
    boxes [px] (NaN where the boxes are not the same objects in the same order)."""
    stored = read_image_file(path)
    ways = {"as stored (8-bit)": stored, "read_image (float)": read_image(path),
            "16-bit copy": stored.astype(np.uint16) * 257}
    reference = detector.detect(stored)
    rows = []
    for name, pixels in ways.items():
        found = detector.detect(pixels)
        same = [f.obj_id for f in found] == [r.obj_id for r in reference]
        moved = float(np.abs(np.subtract([f.box for f in found], [r.box for r in reference])).max(initial=0.0)) \
            if same else float("nan")
        rows.append([name, len(found), moved])
    return rows


def pads(detector: Detector, path: Path, instances: list[dict], values: dict[str, float]) -> list[list]:
    """Per pad value, over the four crops: boxes centred in the pad and the instances inside found; and the boxes
    on a frame of that grey alone."""
    grey = read_image(path)
    rows = []
    for name, value in values.items():
        in_pad = found = inside = 0
        for x, y, width, height in CROPS.values():
            padded = np.full(grey.shape, value, np.float32)
            top, left = (grey.shape[0] - height) // 2, (grey.shape[1] - width) // 2
            padded[top:top + height, left:left + width] = grey[y:y + height, x:x + width]
            boxes = [(d.obj_id, (d.box[0] - left + x, d.box[1] - top + y, d.box[2], d.box[3]))
                     for d in detector.detect(padded)]
            in_pad += sum(not (x <= b[0] + b[2] / 2 < x + width and y <= b[1] + b[3] / 2 < y + height)
                          for _, b in boxes)
            held = [i for i in instances  # wholly inside the crop
                    if box_intersection(i["bbox_obj"], (x, y, width, height)) >= i["bbox_obj"][2] * i["bbox_obj"][3]]
            found += _found(boxes, held)
            inside += len(held)
        blank = len(detector.detect(np.full(grey.shape, value, np.float32)))
        rows.append([name, in_pad, f"{found} / {inside}", blank])
    return rows


def _found(boxes: list[tuple[int, tuple[float, ...]]], instances: list[dict]) -> int:
    """Instances with a box of their object at IoU >= MATCH_IOU."""
    return sum(any(o == i["obj_id"] and box_iou(i["bbox_obj"], b) >= MATCH_IOU for o, b in boxes) for i in instances)


def larger(detector: Detector, path: Path, instances: list[dict]) -> list[list]:
    """Per larger frame holding the bin: the detector's scale against the bin's own, boxes, instances found."""
    stored = read_image_file(path)
    own = min(detector.metadata.input_width / stored.shape[1], detector.metadata.input_height / stored.shape[0])
    rows = [["the bin frame itself, 720 x 540", 1.0, len(found := detector.detect(stored)),
             _found([(d.obj_id, d.box) for d in found], instances)]]
    for name, (cols, height, x, y) in LARGER.items():
        frame = np.full((height, cols), FILL, np.uint8)
        frame[y:y + stored.shape[0], x:x + stored.shape[1]] = stored
        found = detector.detect(frame)
        scale = min(detector.metadata.input_width / cols, detector.metadata.input_height / height) / own
        rows.append([name, scale, len(found), _found([(d.obj_id, (d.box[0] - x, d.box[1] - y, *d.box[2:]))
                                                      for d in found], instances)])
    return rows


def main() -> None:
    detector = Detector(DETECTOR)
    path, instances = _sample()
    mean = float(read_image(path).mean())
    reading_rows, larger_rows = readings(detector, path), larger(detector, path, instances)
    pad_rows = pads(detector, path, instances, {
        "0 (black)": 0.0, f"{DETECTOR_INPUT_MEAN:g} (the graph's mean: the letterbox's)": DETECTOR_INPUT_MEAN,
        "0.5": 0.5, f"the frame's mean ({mean:.3f})": mean, "1 (white)": 1.0})
    markdown = "\n\n".join([
        "# The frame path: one reading of the frame, and the letterbox's pad",
        "`python -m bench.frame_path`: the shipped detector (its own thresholds) on `models/samples/bin.png`.",
        "## Boxes however the file is read",
        "Before issue 62 the file as stored was resized as 8-bit and `read_image`'s float frame as float: 33 "
        "boxes against 32, apart by up to half a pixel. Now every reading is made grey float first:",
        markdown_table(["reading", "boxes", "largest edge difference from the stored file's [px]"],
                       [[name, str(count), f"{moved:.4f}"] for name, count, moved in reading_rows]),
        "## The letterbox's pad",
        "Four crops of the frame at the detector's own scale (16:9 from the top and bottom, 3:4 from the left and "
        "right), padded to 4:3 by hand with each value; instances: wholly inside a crop, found with their object "
        f"at IoU >= {MATCH_IOU}.",
        markdown_table(["pad value", "boxes centred in the pad", "instances found", "boxes on a frame of this grey"],
                       [[name, str(in_pad), found, str(blank)] for name, in_pad, found, blank in pad_rows]),
        "## Frames of another aspect: the parts seen smaller",
        f"The bin frame inside larger frames (the rest grey {FILL}; the 16:9 and portrait ones letterboxed): the "
        "detector sees it at a share of its own scale; it was trained at its own scale and larger (zoom 1 to "
        "1.6), so recall falls with the scale, in a 4:3 frame without pad as much as in the 16:9 frame of that "
        "scale.",
        markdown_table(["frame", "scale (the bin's own = 1)", "boxes", f"instances found (of {len(instances)})"],
                       [[name, f"{scale:.2f}", str(count), str(found)] for name, scale, count, found in larger_rows]),
        machine_line(machine())])
    write_results(RESULTS, "frame-path", {"readings": reading_rows, "pads": pad_rows, "larger": larger_rows},
                  markdown)
    print(markdown)


if __name__ == "__main__":
    run_command("bench.frame_path", main)
