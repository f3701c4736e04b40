"""Does a quantised model decode the float model's pose? Agreement on the crops of a BOP split.

    python -m bench.agreement MODEL.onnx QUANTISED.onnx [...] \
        --split DIR [--models-dir DIR] [--out DIR]

``bench/latency.py`` measures agreement with random weights; this measures it
for trained models on held-out crops (the export's own figure uses the parity
crops that int8 was calibrated on). Every ground-truth instance of the split
(at least 10 % visible) of an object the model knows is cropped by the runtime
from its box, every model runs on the same crops, and each quantised model is
compared with the float one: the argmax agreement (same winning neuron) and
the pose agreement (same argmax-decoded rotation up to the object's
symmetries, :func:`popcode_trainer.export.agreement.pose_agreement`), over all crops and
per object.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.crop import read_image
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.inference.image_loop import group_by_image
from popcode_trainer.data.bop import Instance
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.export.agreement import compare
from tools.command import run_command
from tools.report import write_results


def split_crops(estimator: PoseEstimator, instances: Sequence[Instance]) -> tuple[np.ndarray, np.ndarray]:
    """The runtime's crops ``(N, 1, S, S)`` of the instances, read image by image, and their object ids."""
    crops, obj_ids = [], []
    for image in tqdm(group_by_image(instances), desc="crops", unit="image"):
        crops.append(estimator.crops(read_image(image.path), image.boxes))
        obj_ids += image.obj_ids
    return np.concatenate(crops), np.array(obj_ids)


def measure(float_path: Path, quantised_paths: Sequence[Path], split_dir: Path,
            models_dir: Path) -> list[dict[str, Any]]:
    """One record per quantised model and object (``obj_id`` ``all`` for every crop)."""
    reference_model = PoseEstimator(float_path)
    metadata = reference_model.metadata
    split = read_eval_split([split_dir], models_dir, obj_ids=sorted(metadata.objects))
    if not split.instances:
        raise PopcodeError(f"{split_dir} has no instance of the model's objects {sorted(metadata.objects)}")
    crops, obj_ids = split_crops(reference_model, split.instances)
    reference = reference_model.run(crops)
    records = []
    for path in quantised_paths:
        output = PoseEstimator(path).run(crops)
        if output.shape != reference.shape:
            raise PopcodeError(f"{path} outputs {output.shape[1]} values per crop, {float_path} {reference.shape[1]}")
        for obj_id in ["all", *sorted(set(obj_ids.tolist()))]:
            chosen = np.ones(len(obj_ids), bool) if obj_id == "all" else obj_ids == obj_id
            result = compare(path, output[chosen], reference[chosen], metadata, obj_ids[chosen])
            records.append({"model": path.name, "float_model": float_path.name, "obj_id": obj_id,
                            "crops": int(chosen.sum()), "argmax_agreement": result.argmax_agreement,
                            "pose_agreement": result.pose_agreement, "max_abs_diff": result.max_abs_diff})
    return records


def render_markdown(records: Sequence[dict[str, Any]], split_dir: Path) -> str:
    rows = [[r["model"], r["obj_id"], r["crops"], f"{100 * r['argmax_agreement']:.1f} %",
             f"{100 * r['pose_agreement']:.1f} %", f"{r['max_abs_diff']:.3g}"] for r in records]
    return (f"Agreement with the float model on the crops of `{split_dir}`.\n\n"
            + markdown_table(["model", "object", "crops", "argmax agreement", "pose agreement", "max abs diff"], rows))


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("float_model", type=Path, help="the float ONNX model (the reference)")
    parser.add_argument("quantised", type=Path, nargs="+", help="quantised copies of it (e.g. model.int8.onnx)")
    parser.add_argument("--split", type=Path, required=True, help="a BOP split folder the models did not train on")
    parser.add_argument("--models-dir", type=Path, default=None,
                        help="the objects' models folder (default: SPLIT/models, where rendered splits keep it)")
    parser.add_argument("--out", type=Path, default=Path("bench/results"), help="folder for agreement.json/.md")
    parser.add_argument("--name", default="agreement", help="file name stem of the results")
    args = parser.parse_args(argv)
    records = measure(args.float_model, args.quantised, args.split, args.models_dir or args.split / "models")
    markdown = render_markdown(records, args.split)
    write_results(args.out, args.name, {"split": str(args.split), "records": records}, markdown)
    print(markdown)
    return records


if __name__ == "__main__":
    run_command("bench.agreement", main)
