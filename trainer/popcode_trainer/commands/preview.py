"""``popcode-train preview``: a PNG grid of augmented training crops beside their population-code targets.

The analogue of the paper's Fig. 1/3: each crop is followed by its target, drawn as the activation
of every preferred axis on a world map of the sphere (longitude = azimuth, latitude = elevation;
for the full code the maximum over angles). A symmetric object shows one peak per equivalent pose.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from popcode_runtime import CodeLayout, symmetry_class  # noqa: E402
from popcode_runtime.code import fibonacci_lattice  # noqa: E402

from ..data.augment import Augmentation  # noqa: E402
from ..data.bop import read_bop_split  # noqa: E402
from ..data.samples import CropDataset, population_code_target  # noqa: E402

_PAIRS_PER_ROW = 4


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "preview", help="PNG grid of augmented training crops and their targets",
        description="Write a PNG grid of training crops as the network sees them (augmented unless "
                    "--no-augmentation), each beside its population-code target drawn on a map of the sphere.")
    parser.add_argument("--split", required=True, type=Path, help="BOP split folder")
    parser.add_argument("--models", type=Path, help="models folder (default: SPLIT/models)")
    parser.add_argument("--out", required=True, type=Path, help="PNG to write")
    parser.add_argument("--count", type=int, default=12, help="number of crops")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--obj-ids", nargs="+", type=int)
    parser.add_argument("--backgrounds", type=Path, help="folder of background images (default: procedural)")
    parser.add_argument("--no-augmentation", action="store_true")
    parser.set_defaults(handler=run)


def axis_activation(code: np.ndarray, n_axes: int) -> np.ndarray:
    """Activation per preferred axis: the axis-only code itself, else the maximum over angles."""
    return code if code.size == n_axes else code.reshape(n_axes, -1).max(axis=1)


def write_preview(dataset: CropDataset, indices: list[int], layout: CodeLayout, models_info: dict, out: Path) -> None:
    """Draw crops and targets of ``indices`` into a PNG at ``out``."""
    axes_xyz = fibonacci_lattice(layout.n_axes)
    longitude, latitude = np.arctan2(axes_xyz[:, 1], axes_xyz[:, 0]), np.arcsin(np.clip(axes_xyz[:, 2], -1, 1))
    rows = -(-len(indices) // _PAIRS_PER_ROW)
    figure = plt.figure(figsize=(4.2 * _PAIRS_PER_ROW, 2.0 * rows))
    for slot, index in enumerate(indices):
        sample = dataset[index]
        image_ax = figure.add_subplot(rows, 2 * _PAIRS_PER_ROW, 2 * slot + 1)
        image_ax.imshow(sample["image"][0].numpy(), cmap="gray", vmin=0.0, vmax=1.0)
        image_ax.set_axis_off()
        kind = symmetry_class(models_info[sample["obj_id"]]).value
        image_ax.set_title(f"obj {sample['obj_id']} ({kind})", fontsize=8)
        code_ax = figure.add_subplot(rows, 2 * _PAIRS_PER_ROW, 2 * slot + 2, projection="mollweide")
        activation = axis_activation(sample["target"].numpy(), layout.n_axes)
        order = np.argsort(activation)  # strongest on top
        code_ax.scatter(longitude[order], latitude[order], c=activation[order], s=2, cmap="viridis", vmin=0.0)
        code_ax.set_xticklabels([])
        code_ax.set_yticklabels([])
        code_ax.set_title(f"target, peak {activation.max():.2f}", fontsize=8)
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=100)
    plt.close(figure)


def run(args: argparse.Namespace) -> int:
    models_dir = args.models or args.split / "models"
    split = read_bop_split(args.split, models_dir, obj_ids=args.obj_ids)
    layout = CodeLayout()
    dataset = CropDataset(split.instances, population_code_target(split.models_info, layout),
                          augmentation=None if args.no_augmentation else Augmentation(),
                          backgrounds=args.backgrounds, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    count = min(args.count, len(dataset))
    indices = sorted(rng.choice(len(dataset), size=count, replace=False).tolist())
    write_preview(dataset, indices, layout, split.models_info, args.out)
    print(f"preview of {count} crops written to {args.out}")
    return 0
