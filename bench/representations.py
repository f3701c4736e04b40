"""Population code vs the baselines on the built-in objects, with the BOP metrics (paper Tables III, IV).

    python -m bench.representations --quick [--out DIR]
    python -m bench.representations --full  [--out DIR]
    python -m bench.representations --smoke [--out DIR]

Renders a training split and a separate test split (random positions, other
seed), trains every representation with the same network, data, augmentation
and budget, exports each to ONNX and evaluates it through the runtime with the
argmax decoder (and the population code once more with the refined decoder).
Objects are pooled as the paper pooled T-LESS objects: one model for the
objects with a continuous symmetry about the same axis (axis-only code), one
for the others (full code). Interrupted runs resume: rendering skips finished
images, training resumes from its last checkpoint, finished exports are kept.
``--smoke`` runs it all with a tiny network on a few images: a check of the
script, not a measurement.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.geometry.symmetries import SymmetryClass, symmetry_class
from popcode_runtime.inference.benchmark import machine_description
from popcode_runtime.model.metadata import Representation
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.demo.steps import (
    PipelineSize,
    object_groups,
    render_splits,
    small_config,
    train_and_export,
)
from popcode_trainer.eval.pipeline.evaluate import MethodResult, evaluate_models
from popcode_trainer.eval.pipeline.instance_code import instance_code
from popcode_trainer.eval.pipeline.models import Method, load_model
from popcode_trainer.eval.pipeline.split import EvalSplit, read_eval_split
from popcode_trainer.eval.reporting.figures import plot_instance_code
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.eval.reporting.report import report_dict, write_report
from popcode_trainer.eval.reporting.tables import methods_markdown, to_json
from popcode_trainer.metrics.recall import GROUPS
from popcode_trainer.train.config import Config, DataConfig
from tools.command import run_command
from tools.paths import RESULTS
from tools.recipes import NETWORKS

REFINED = "population_code (refined)"
PAPER_METHODS = {Representation.SINGLE_VARIABLE: "Single Variable", Representation.ONE_HOT: "One Hot Vector",
                 Representation.POPULATION_CODE: "Population Code"}
# Paper Table IV (T-LESS, 30 objects): VSD, MSSD, MSPD, e_VSD<0.3 in %.
PAPER_TABLE_IV = {
    "Without ambiguity": {"Single Variable": (73.41, 83.35, 85.74, 84.74),
                          "One Hot Vector": (65.26, 73.27, 75.89, 78.81),
                          "Population Code": (75.33, 84.68, 86.07, 88.04)},
    "With ambiguity": {"Single Variable": (44.70, 49.60, 43.51, 43.01),
                       "One Hot Vector": (43.17, 40.12, 35.31, 43.04),
                       "Population Code": (72.59, 84.74, 79.61, 86.23)},
    "All objects": {"Single Variable": (61.77, 69.67, 68.62, 67.82),
                    "One Hot Vector": (56.31, 59.83, 59.44, 64.31),
                    "Population Code": (74.22, 84.70, 83.46, 87.31)},
}
PAPER_TABLE_IV_METRICS = ("VSD", "MSSD", "MSPD", "e_VSD<0.3")
# Paper Table III: MSSD % of T-LESS objects 1..30 and their symmetry ("c" continuous, "n" none, else the order).
PAPER_SYMMETRY = "cccc222222" "22cccccn22" "nn2c22422c"
PAPER_TABLE_III = {
    "Single Variable": (80.4, 80.9, 90.3, 84.1, 66.0, 64.9, 21.9, 34.9, 58.7, 64.0, 74.5, 73.5, 86.6, 84.1, 93.5,
                        89.0, 94.4, 85.2, 47.7, 34.0, 62.7, 64.0, 66.4, 92.4, 75.9, 79.8, 7.8, 15.8, 18.6, 89.7),
    "One Hot Vector": (71.0, 74.5, 82.1, 78.5, 69.0, 50.7, 41.5, 30.9, 41.6, 51.5, 60.9, 62.2, 84.0, 84.9, 86.4,
                       87.4, 88.0, 44.3, 35.0, 19.1, 34.5, 27.8, 34.6, 86.2, 41.3, 34.9, 17.8, 20.7, 31.2, 87.4),
    "Population Code": (81.8, 84.1, 91.6, 86.8, 89.6, 91.5, 83.2, 89.1, 92.2, 92.5, 86.8, 84.9, 90.9, 86.1, 95.8,
                        93.0, 96.1, 75.9, 82.6, 74.0, 60.1, 59.7, 89.0, 93.9, 83.5, 85.3, 58.9, 79.2, 88.3, 94.0),
}
SYMMETRY_NAMES = {"c": "continuous", "n": "none", "2": "2-fold", "4": "4-fold"}


SIZES = {
    # About 25 minutes on 2 shared CPU cores: a 642 x 36 code and a network of a few per cent of the paper's width.
    "quick": PipelineSize(400, 50, small_config(epochs=12, n_axes=642, n_angles=36)),
    # The paper's code, network and schedule (Config()'s defaults); for a GPU.
    "full": PipelineSize(8000, 200, Config(data=DataConfig(num_workers=8))),
    # A tiny network and code on a few images: every file and table of a run, in seconds; the numbers mean nothing.
    "smoke": PipelineSize(4, 1, small_config(epochs=1, n_axes=42, n_angles=12, network=NETWORKS["tiny"], sigma_deg=30.0,
                                             batch_size=4, num_hypotheses=4)),
}


def paper_table_iv_markdown() -> str:
    sections = []
    for group in GROUPS:
        scores = {method: dict(zip(PAPER_TABLE_IV_METRICS, (v / 100 for v in values), strict=True))
                  for method, values in PAPER_TABLE_IV[group].items()}
        sections.append(f"**{group}** (paper)\n\n{methods_markdown(scores)}")
    return "\n\n".join(sections)


def paper_mssd_by_symmetry() -> dict[str, dict[str, float]]:
    """The paper's Table III averaged over the T-LESS objects of each symmetry kind (MSSD, fraction)."""
    result = {}
    for method, values in PAPER_TABLE_III.items():
        result[method] = {
            SYMMETRY_NAMES[kind]: float(np.mean([v for v, k in zip(values, PAPER_SYMMETRY, strict=True) if k == kind]))
            / 100
            for kind in "cn24"
        }
    return result


def symmetry_markdown(by_method: Mapping[str, Mapping[str, float]]) -> str:
    kinds = list(SYMMETRY_NAMES.values())
    rows = [[method, *(f"{100 * scores[k]:.1f}%" if k in scores else "–" for k in kinds)]
            for method, scores in by_method.items()]
    return markdown_table(["MSSD / symmetry", *kinds], rows)


def ours_mssd_by_symmetry(results: Sequence[MethodResult], models_info: Mapping[int, Mapping[str, Any]],
                          ) -> dict[str, dict[str, float]]:
    """Our per-object MSSD averaged over the built-in objects of each symmetry kind, as the paper's above."""
    def kind(info: Mapping[str, Any]) -> str:
        if symmetry_class(info) is SymmetryClass.CONTINUOUS:
            return "continuous"
        order = len(info.get("symmetries_discrete", [])) + 1
        return "none" if order == 1 else f"{order}-fold"

    kinds = {obj_id: kind(models_info[obj_id]) for obj_id in results[0].per_object}
    return {r.name: {k: float(np.mean([r.per_object[o]["MSSD"] for o in kinds if kinds[o] == k]))
                     for k in sorted(set(kinds.values()))} for r in results}


def code_figures(method: Method, split: EvalSplit, out_dir: Path) -> list[Path]:
    """The paper's Fig. 5 analogue: predicted vs target code of the first test crop of each model's objects."""
    paths = []
    for model in method.models:
        instance = next(inst for inst in split.instances if inst.obj_id in model.obj_ids)
        path = out_dir / f"code_obj{instance.obj_id}.png"
        paths.append(plot_instance_code(instance_code(model.estimator, instance), path))
    return paths


def run_benchmark(size: PipelineSize, out_dir: Path, size_name: str) -> dict[str, Any]:
    """Render, train, export, evaluate; writes the report files and returns the JSON record."""
    started = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    train_split, test_split = render_splits(size, out_dir)
    models_info = load_models_info(train_split / BUILTIN_MODELS_FOLDER)
    groups = object_groups(models_info)
    methods, train_seconds = [], {}
    for representation in size.representations:
        paths = []
        for obj_ids in groups:
            path, seconds = train_and_export(size, representation, obj_ids, train_split, out_dir)
            paths.append(path)
            train_seconds[f"{representation} {obj_ids}"] = seconds
        methods.append(Method(representation, tuple(load_model(p) for p in paths)))
        if representation == Representation.POPULATION_CODE:
            methods.append(Method(REFINED, tuple(load_model(p, decoder="refined") for p in paths)))
    split = read_eval_split([test_split], test_split / BUILTIN_MODELS_FOLDER)
    results = evaluate_models(methods, split)
    write_report(results, out_dir / "eval")
    figures = code_figures(next(m for m in methods if m.name == Representation.POPULATION_CODE), split, out_dir)
    ours_by_symmetry = ours_mssd_by_symmetry(results, models_info)
    record = {
        "benchmark": "representations",
        "size": size_name,
        "settings": asdict(size),
        "object_groups": groups,
        "machine": {**machine_description(), "torch": torch.__version__,
                    "device": "cuda" if torch.cuda.is_available() else "cpu"},
        "train_seconds": train_seconds,
        "wall_seconds": time.perf_counter() - started,
        "results": report_dict(results),
        "code_figures": [str(path) for path in figures],
        "mssd_by_symmetry": ours_by_symmetry,
        "paper": {"table_iv_percent": PAPER_TABLE_IV, "mssd_by_symmetry": paper_mssd_by_symmetry()},
    }
    write_bytes_atomic(out_dir / "representations.json", (to_json(record) + "\n").encode())
    markdown = "\n\n".join([
        f"# Representations on the built-in objects ({size_name})",
        f"Machine: {record['machine']['cpu']}, {record['machine']['cores']} cores, {record['machine']['device']}; "
        f"wall time {record['wall_seconds'] / 60:.1f} min. Groups trained together: {groups}. "
        f"{size.train_images_per_object} training / {size.test_images_per_object} test images per object, "
        f"{size.config.train.epochs} epochs, code {size.config.code.n_axes} x {size.config.code.n_angles}.",
        (out_dir / "eval" / "report.md").read_text().strip(),
        "## MSSD by symmetry kind: ours (built-in objects) and the paper's (T-LESS, Table III averaged)",
        symmetry_markdown(ours_by_symmetry),
        symmetry_markdown(paper_mssd_by_symmetry()),
        "## The paper's Table IV (T-LESS)",
        paper_table_iv_markdown(),
    ]) + "\n"
    write_bytes_atomic(out_dir / "representations.md", markdown.encode())
    print(markdown)
    return record


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    chosen = parser.add_mutually_exclusive_group(required=True)
    chosen.add_argument("--quick", action="store_const", const="quick", dest="size",
                        help="small code and network; under 30 minutes on 2 CPU cores")
    chosen.add_argument("--full", action="store_const", const="full", dest="size",
                        help="the paper's code and network (for a GPU)")
    chosen.add_argument("--smoke", action="store_const", const="smoke", dest="size",
                        help="a tiny network on a few images: a check of the script, not a measurement")
    parser.add_argument("--epochs", type=int, default=None, help="train this many epochs instead of the size's")
    parser.add_argument("--out", type=Path, default=None,
                        help="output folder (default: bench/results/representations-SIZE)")
    args = parser.parse_args(argv)
    out_dir = args.out or RESULTS / f"representations-{args.size}"
    size = SIZES[args.size] if args.epochs is None else SIZES[args.size].with_epochs(args.epochs)
    run_benchmark(size, out_dir, args.size)


if __name__ == "__main__":
    run_command("bench.representations", main)
