"""``popcode-train preview``: a PNG grid of augmented training crops beside their population-code targets.

The analogue of the paper's Fig. 1/3: each crop is followed by its target, drawn as the activation
of every preferred axis on a world map of the sphere (longitude = azimuth, latitude = elevation;
for the full code the maximum over angles). A symmetric object shows one peak per equivalent pose.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import OVERWRITE_HELP, check_picture_path
from popcode_runtime.coding.population_code import CodeLayout
from popcode_runtime.geometry.symmetries import symmetry_class

from ..data.augment import Augmentation
from ..data.bop import read_bop_split
from ..data.samples import CropDataset
from ..eval.reporting.figures import axis_activations, save_figure, sphere_panel
from ..train.representations import PerObjectPopulationCodes

_PAIRS_PER_ROW = 4


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "preview", help="PNG grid of augmented training crops and their targets",
        description="Write a PNG grid of training crops as the network sees them (augmented unless "
                    "--no-augmentation), each beside its population-code target drawn on a map of the sphere.")
    parser.add_argument("--split", required=True, type=Path, help="BOP split folder")
    parser.add_argument("--models", type=Path, help="models folder (default: SPLIT/models)")
    parser.add_argument("--out", required=True, type=Path, help="PNG to write")
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    parser.add_argument("--count", type=int, default=12, help="number of crops")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--obj-ids", nargs="+", type=int)
    parser.add_argument("--backgrounds", type=Path, help="folder of background images (default: procedural)")
    parser.add_argument("--no-augmentation", action="store_true")
    parser.set_defaults(handler=run)


def write_preview(dataset: CropDataset, indices: list[int], codes: PerObjectPopulationCodes, models_info: dict,
                  out: Path) -> None:
    """Draw crops and targets of ``indices`` into a PNG at ``out``, each target in its object's layout."""
    rows = -(-len(indices) // _PAIRS_PER_ROW)
    # A bare Figure renders with the Agg canvas and leaves pyplot's global state alone.
    figure = Figure(figsize=(4.2 * _PAIRS_PER_ROW, 2.0 * rows), dpi=100)
    for slot, index in enumerate(indices):
        sample = dataset[index]
        image_ax = figure.add_subplot(rows, 2 * _PAIRS_PER_ROW, 2 * slot + 1)
        image_ax.imshow(sample["image"][0].numpy(), cmap="gray", vmin=0.0, vmax=1.0)
        image_ax.set_axis_off()
        kind = symmetry_class(models_info[sample["obj_id"]]).value
        image_ax.set_title(f"obj {sample['obj_id']} ({kind})", fontsize=8)
        layout = codes.layout(sample["obj_id"])
        activation = axis_activations(layout, sample["target"].numpy())
        peak = float(activation.max())
        code_ax = sphere_panel(figure, (rows, 2 * _PAIRS_PER_ROW, 2 * slot + 2), layout, activation,
                               f"target, peak {peak:.2f}", vmax=max(peak, 1e-6), colorbar=False, fontsize=8)
        code_ax.set_yticklabels([])
    save_figure(figure, out)


def run(args: argparse.Namespace) -> int:
    if args.count < 1:
        raise PopcodeError(f"--count must be at least 1, got {args.count}")
    models_dir = args.models or args.split / "models"
    check_picture_path(args.out, "--out", [args.split, models_dir, *filter(None, [args.backgrounds])], args.overwrite)
    split = read_bop_split(args.split, models_dir, obj_ids=args.obj_ids)
    paper = CodeLayout()
    codes = PerObjectPopulationCodes(split.models_info, paper.n_axes, paper.n_angles, paper.sigma_deg)
    dataset = CropDataset(split.instances, codes.targets,
                          augmentation=None if args.no_augmentation else Augmentation(),
                          backgrounds=args.backgrounds, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    count = min(args.count, len(dataset))
    indices = sorted(rng.choice(len(dataset), size=count, replace=False).tolist())
    write_preview(dataset, indices, codes, split.models_info, args.out)
    print(f"preview of {count} crops written to {args.out}")
    return 0
