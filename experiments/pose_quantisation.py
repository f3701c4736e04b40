"""Which quantisation brings the shipped pose models to about a millisecond a crop without losing the bin's accuracy
(issue 52): each shipped model against its quantised copies, on the validation splits and on this CPU.

    python -m experiments.pose_quantisation [--models M12.onnx M36.onnx] [--work runs/pose_quantisation]
        [--images 40] [--scenes 80] [--calibration-images 30] [--calibration-scenes 20] [--kinds int8 int8-nbits8]
        [--name pose-quantisation]

``--models``: the pair to start from, by default the shipped files. The recorded run started from the files of
commit 38d6885 (``git show 38d6885:models/builtin-parts-3-6.onnx``), whose 3-6 model was ``nbits8-fp16``; the 3-6
model shipped since is that run's ``int8-nbits8`` copy. The files keep no float copy, so the float weights are read
back from them (:func:`float_copy`: half-precision weights widened, 8-bit output blocks expanded to their values)
and each kind is quantised from those by the exporter's own ``export.quantise``. int8 ranges are calibrated on the
runtime's crops of splits rendered with the demo's training seeds (0 single parts, 3000 bin scenes), never on the
validation splits. Every copy is scored with ``popcode-train evaluate`` (argmax, instances at least 10 % visible) on
the validation splits (clean single parts, seed 5000; bin, industrial camera, seed 4000; the bin again with
detector-like boxes), paired with the shipped pair on the same instances (bootstrap 95 % interval), and timed with
``popcode bench`` (one thread, batch 1 and 8, end to end and inference). ``--work`` keeps splits, copies and scores:
a rerun resumes. Results: ``bench/results/<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import numpy_helper

from bench.agreement import split_crops
from experiments.path_traced_gap import instance_scores, paired
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_trainer.cli import main as trainer
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.export.model_io import read_onnx_metadata, save_onnx
from popcode_trainer.export.quantise import quantise
from tools.command import run_command
from tools.paths import RESULTS, ROOT, SHIPPED_1_2, SHIPPED_3_6
from tools.report import machine, machine_line, write_results

SPLITS = {  # name: render options
    "clean_rendered": ["--images", "{images}", "--seed", "5000"],
    "bin_rendered": ["--scenes", "{scenes}", "--seed", "4000", "--sensor", "industrial"],
    "calibration_clean": ["--images", "{calibration_images}", "--seed", "0"],
    "calibration_bin": ["--scenes", "{calibration_scenes}", "--seed", "3000", "--sensor", "industrial"],
}
SCORED = {"clean": ("clean", ()), "bin": ("bin", ()),
          "bin, detector-like boxes": ("bin", ("--box-noise", "detector", "--box-noise-seed", "0"))}
BATCHES = (1, 8)


def _trainer(argv: list[str]) -> None:
    if trainer(argv) != 0:
        raise SystemExit(f"popcode-train {' '.join(argv)} failed")


def float_copy(model: onnx.ModelProto) -> onnx.ModelProto:
    """The float graph a shipped file computes: fp16 weights (read through ``Cast``) widened back to float32 and
    every ``MatMulNBits`` (8-bit, symmetric) replaced by a ``MatMul`` of its blocks' values."""
    initializers = {init.name: init for init in model.graph.initializer}
    nodes = []
    for node in model.graph.node:
        source = initializers.get(node.input[0]) if node.input else None
        if node.op_type == "Cast" and source is not None and source.data_type == onnx.TensorProto.FLOAT16:
            widened = numpy_helper.from_array(numpy_helper.to_array(source).astype(np.float32), node.output[0])
            model.graph.initializer.remove(source)
            model.graph.initializer.append(widened)
            initializers[node.output[0]] = widened
            continue
        nodes.append(node)
    for index, node in enumerate(nodes):
        if node.op_type != "MatMulNBits":
            continue
        attributes = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        if attributes["bits"] != 8 or len(node.input) != 3:
            raise SystemExit(f"{node.name}: only 8-bit MatMulNBits without zero points is read back")
        rows, columns = attributes["K"], attributes["N"]
        packed = numpy_helper.to_array(initializers[node.input[1]]).astype(np.float32)  # [N, blocks, block]
        scales = numpy_helper.to_array(initializers[node.input[2]]).reshape(columns, -1, 1)
        weight = ((packed - 128.0) * scales).reshape(columns, -1)[:, :rows].T  # [K, N]
        name = f"{node.input[1]}.float"
        model.graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(weight, np.float32), name))
        nodes[index] = onnx.helper.make_node("MatMul", [node.input[0], name], list(node.output), name=node.name)
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    used = {name for node in model.graph.node for name in node.input}
    for init in [init for init in model.graph.initializer if init.name not in used]:
        model.graph.initializer.remove(init)
    return onnx.shape_inference.infer_shapes(model)


def prepare(work: Path, sizes: dict[str, int], models: Sequence[Path], kinds: Sequence[str]
            ) -> dict[str, list[Path]]:
    """Render the splits (resumes) and write each model's float and quantised copies; the file of each
    (model, kind), ``shipped`` (the models as given) included."""
    for split, options in SPLITS.items():
        _trainer(["render", "--objects", "builtin", "--out", str(work / split), "--quiet",
                  *[option.format(**sizes) for option in options]])
    copies: dict[str, list[Path]] = {"shipped": list(models), "float": []}
    copies.update({kind: [] for kind in kinds})
    for shipped in models:
        metadata = read_onnx_metadata(shipped)
        float_path = work / "copies" / f"{shipped.stem}.onnx"
        if not float_path.is_file():
            float_path.parent.mkdir(parents=True, exist_ok=True)
            save_onnx(float_copy(onnx.load(str(shipped))), metadata, float_path)
        copies["float"].append(float_path)
        crops = calibration_crops(work, float_path)
        for kind in kinds:
            path = float_path.with_name(f"{float_path.stem}.{kind}.onnx")
            copies[kind].append(path if path.is_file() else quantise(float_path, kind, metadata, crops))
    return copies


def calibration_crops(work: Path, model_path: Path) -> np.ndarray:
    """The runtime's crops of every instance (>= 10 % visible) of the model's objects in the calibration splits,
    single parts and bin scenes alike."""
    estimator = PoseEstimator(model_path)
    crops = []
    for split in ("calibration_clean", "calibration_bin"):
        instances = read_eval_split([work / split], work / split / "models", sorted(estimator.metadata.objects),
                                    min_visib_fract=0.1).instances
        crops.append(split_crops(estimator, instances)[0])
    return np.concatenate(crops)


def latency(path: Path) -> dict[str, float]:
    """``popcode bench``'s median ms at batch 1 and 8 on one thread, end to end and inference alone."""
    out = subprocess.run([sys.executable, "-m", "popcode_runtime.commands.cli", "bench", str(path), "--threads", "1",
                          *[option for batch in BATCHES for option in ("--batch", str(batch))],
                          "--iterations", "200", "--json"], check=True, capture_output=True, text=True).stdout
    rows = json.loads(out)["results"]
    return {f"{row['stage']}_batch{row['batch']}_ms": row["median_ms"] for row in rows}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", type=Path, nargs=2, default=[SHIPPED_1_2, SHIPPED_3_6], metavar="MODEL",
                        help="the 1-2 and 3-6 models to quantise (default: the shipped files)")
    parser.add_argument("--work", type=Path, default=Path("runs/pose_quantisation"))
    parser.add_argument("--images", type=int, default=40, help="clean validation images a part")
    parser.add_argument("--scenes", type=int, default=80, help="validation bin scenes")
    parser.add_argument("--calibration-images", type=int, default=30, help="calibration images a part")
    parser.add_argument("--calibration-scenes", type=int, default=20, help="calibration bin scenes")
    parser.add_argument("--kinds", nargs="+", default=["int8", "int8-nbits8"])
    parser.add_argument("--name", default="pose-quantisation")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    sizes = {"images": args.images, "scenes": args.scenes, "calibration_images": args.calibration_images,
             "calibration_scenes": args.calibration_scenes}
    copies = prepare(args.work, sizes, args.models, args.kinds)
    scores = {kind: {name: instance_scores(args.work, split, "rendered",
                                           kind.replace("-", "_") + ("_detector" if options else ""), models,
                                           options=options)
                     for name, (split, options) in SCORED.items()}
              for kind, models in copies.items()}
    results: dict[str, Any] = {}
    for kind, models in copies.items():
        results[kind] = {"files": [str(path.relative_to(ROOT) if path.is_relative_to(ROOT) else path)
                                   for path in models],
                         "megabytes": [round(path.stat().st_size / 1e6, 2) for path in models],
                         "latency": {path.stem.split(".")[0]: latency(path) for path in models},
                         "scores": {name: vars(paired(scores["shipped"][name], scores[kind][name]))
                                    for name in SCORED}}
    markdown = render(results, args, argv)
    write_results(args.out, args.name, {"sizes": sizes, "results": results}, markdown)
    print(markdown)
    return 0


def render(results: dict[str, Any], args: argparse.Namespace, argv: Sequence[str] | None) -> str:
    score_rows, time_rows = [], []
    for kind, result in results.items():
        cells = []
        for name in SCORED:
            score = result["scores"][name]
            low, high = (100 * value for value in score["interval"])
            cells.append(f"{100 * score['second']:.1f} ({100 * score['difference']:+.1f} [{low:+.1f}, {high:+.1f}])")
        score_rows.append([kind, *cells])
        for model, (megabytes, timing) in zip(("1-2", "3-6"), zip(result["megabytes"], result["latency"].values(),
                                                                    strict=True), strict=True):
            time_rows.append([kind, model, f"{megabytes:.1f}",
                              *[f"{timing[f'{stage}_batch{batch}_ms'] / batch:.2f}" for batch in BATCHES
                                for stage in ("end-to-end", "inference")]])
    return "\n".join([
        f"# {args.name}: the shipped pose models quantised, validation splits and latency",
        "",
        "`" + " ".join(["python -m experiments.pose_quantisation", *(sys.argv[1:] if argv is None else argv)]) + "`",
        "",
        "MSSD % of the pair (1-2 and 3-6 models of one kind) and its paired difference from the shipped pair "
        "(bootstrap 95 % interval):",
        "",
        markdown_table(["kind", *SCORED], score_rows),
        "",
        "Milliseconds a crop, one thread (`popcode bench`, median of 200):",
        "",
        markdown_table(["kind", "model", "MB", *[f"batch {batch} {stage}" for batch in BATCHES
                                                  for stage in ("end to end", "inference")]], time_rows),
        "",
        machine_line(machine()),
    ])


if __name__ == "__main__":
    run_command("experiments.pose_quantisation", main)
