"""Speed and visibility of cluttered scene renders on this machine, and the README's picture of one.

    python -m bench.scene_render [--scenes 40] [--size 720 540] [--sensor industrial] [--picture docs/scene-render.jpg]

Renders the built-in parts as the demo's cluttered test split does (``render_cluttered_test_split``)
into a temporary folder and prints scenes/s, target instances/s and how many instances fall into
each visibility bin. ``--picture`` also writes one rendered image beside its instances' masks:
visible part bright, hidden part dim, the ``bbox_visib`` box and ``visib_fract`` of each.
"""

from __future__ import annotations

import argparse
import colorsys
import json
import platform
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from popcode_runtime.base.files import write_picture_atomic
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.metrics.recall import VISIBILITY_BINS
from tools.command import run_command


def _instance_infos(split: Path) -> list[dict]:
    return [info for path in sorted(split.glob("0*/scene_gt_info.json"))
            for infos in json.loads(path.read_text()).values() for info in infos]


def masks_picture(split: Path, im_id: int) -> np.ndarray:
    """The image of ``im_id`` in scene folder 0 beside its instances' masks, ``(H, 2 W + 4, 3)`` BGR."""
    scene = split / "000000"
    image = cv2.imread(str(next(scene / folder / f"{im_id:06d}.png" for folder in ("gray", "rgb")
                                 if (scene / folder).is_dir())), cv2.IMREAD_COLOR)
    infos = json.loads((scene / "scene_gt_info.json").read_text())[str(im_id)]
    masks = (0.35 * image).astype(np.uint8)
    for index, info in enumerate(infos):
        colour = np.array(colorsys.hsv_to_rgb(index / len(infos), 0.8, 1.0))[::-1] * 255
        whole = cv2.imread(str(scene / "mask" / f"{im_id:06d}_{index:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        visible = cv2.imread(str(scene / "mask_visib" / f"{im_id:06d}_{index:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        masks[whole & ~visible] = (0.35 * colour).astype(np.uint8)
        masks[visible] = colour.astype(np.uint8)
        if info["px_count_visib"]:
            x, y, w, h = info["bbox_visib"]
            cv2.rectangle(masks, (x, y), (x + w, y + h), colour.tolist(), 1)
            cv2.putText(masks, f"{info['visib_fract']:.2f}", (max(x, 2), max(y - 3, 10)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.hstack([image, np.full((image.shape[0], 4, 3), 255, np.uint8), masks])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=40)
    parser.add_argument("--size", nargs=2, type=int, default=(720, 540), metavar=("W", "H"))
    parser.add_argument("--sensor", default="industrial")
    parser.add_argument("--seed", type=int, default=1015)
    parser.add_argument("--picture", type=Path, help="write image 0 beside its masks here (.jpg keeps it small)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        split = render_cluttered_test_split(Path(folder) / "split", args.scenes, tuple(args.size), args.seed,
                                            args.sensor, progress=True)
        seconds = time.perf_counter() - started  # includes writing the built-in models and GL start-up
        visib = np.array([info["visib_fract"] for info in _instance_infos(split)])
        bins = {label: int(((visib >= low) & (visib < high)).sum()) for label, low, high in VISIBILITY_BINS}
        print(json.dumps({
            "machine": platform.processor() or platform.machine(), "scenes": args.scenes, "size": list(args.size),
            "sensor": args.sensor, "seconds": round(seconds, 2), "scenes_per_s": round(args.scenes / seconds, 2),
            "instances": len(visib), "instances_per_s": round(len(visib) / seconds, 1),
            "instances_per_visibility_bin": {**bins, "< 0.1": int((visib < 0.1).sum())},
        }, indent=1))
        if args.picture is not None:
            write_picture_atomic(args.picture, masks_picture(split, 0), [cv2.IMWRITE_JPEG_QUALITY, 85])


if __name__ == "__main__":
    run_command("bench.scene_render", main)
