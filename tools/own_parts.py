"""Parts of our own, unlike the built-in ones, in two sets: tuning parts to choose recipe settings on, and validation
parts to judge the chosen recipe on parts no choice was tuned on.

    python -m tools.own_parts validation --out DIR
    python -m tools.own_parts tuning --out DIR

writes a BOP models folder (``obj_000001.ply`` ... and ``models_info.json``, millimetres, each mesh centred on its
bounding box) that ``popcode-train demo --objects DIR`` (or ``render --objects DIR``) reads. A recipe setting (code
size, sigma, epochs, augmentation) is chosen on the tuning parts; the chosen recipe is then judged once on the
validation parts, never tuned on them, so their score says how the recipe does on parts it has not seen. Each part
stands for a symmetry group or a trap the built-in parts (``popcode_trainer.data.objects``) do not have, each set has
the same kinds of difficulty in other shapes. The validation parts:

1. a 12-tooth gear disc: 12-fold about z and the 12 flips about in-plane axes (dihedral group D12, 24 poses),
2. a round flange with three bolt holes, a hub and three ribs on one face: 3-fold about z, no flip,
3. a bent bracket with unequal legs and off-centre holes: no symmetry,
4. a stepped shaft: continuous symmetry about z, ends differ (no flip),
5. a square flange with a tube, four corner holes and one chamfered corner: it looks 4-fold about z but
   the chamfer breaks it, so it declares nothing (the near-symmetry warning,
   ``popcode_trainer.data.near_symmetry``, reports it: a recipe meets look-alike poses here),
6. a connecting rod (flat link, a thick boss round the big hole, a smaller hole at the other end): 2-fold
   about its long axis x only.

The tuning parts:

1. an L-shaped plate with unequal legs, a boss at the corner and two holes of different sizes: no symmetry,
2. a dog-bone link with a hub round each end hole on one face, one hole wider than the other: it looks
   2-fold about z, but the holes tell the ends apart, so it declares nothing (the near-symmetry warning reports it),
3. a hexagon flange with a bore, six bolt holes and a round boss on one face: 6-fold about z, no flip,
4. a rectangular frame with a centred window and four corner holes: 2-fold about x, y and z (dihedral group
   D2, 4 poses).

The parts are built from :mod:`popcode_trainer.data.solids` (plates with holes, placed solids). Every circle has
a vertex count that the part's rotations map onto itself, so each declared symmetry holds to rounding, and the
symmetry check (``popcode_trainer.data.symmetry_check``) passes them; ``tests/bench/test_own_part_sets.py`` checks
both, and that ``popcode-train demo --objects DIR`` accepts each folder.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from popcode_trainer.data.objects import Z_AXIS, revolve, rotation_4x4, write_models_folder
from popcode_trainer.data.solids import about_z, circle, flips, placed, polar, slab
from tools.command import run_command

_RIM_SECTIONS = 96


def _gear_12() -> trimesh.Trimesh:
    """12-tooth gear disc with a bore: trapezoid teeth centred at multiples of 30 deg, so each tooth and each
    gap lies on a mirror line of the outline."""
    root, tip, sections = 34.0, 42.0, 4  # radii [mm]; arc pieces per root gap and tooth tip
    outline = []
    for tooth in range(12):
        centre = 30.0 * tooth
        outline += [polar(centre - 8.0, root)]
        outline += [polar(angle, tip) for angle in np.linspace(centre - 4.5, centre + 4.5, sections + 1)]
        outline += [polar(angle, root) for angle in np.linspace(centre + 8.0, centre + 22.0, sections + 1)[:-1]]
    return slab(np.array(outline), [circle(10.0)], 12.0)


def _three_rib_flange() -> trimesh.Trimesh:
    """Round flange with a bore and three bolt holes, a hub and three ribs on the top face: 3-fold, no flip."""
    holes = [circle(10.0)] + [circle(5.0, polar(angle, 32.0)) for angle in (90, 210, 330)]
    parts = [slab(circle(45.0, sections=_RIM_SECTIONS), holes, 8.0),
             slab(circle(17.0), [circle(10.0)], 20.0, z0_mm=4.0)]
    for angle in (30, 150, 270):
        rib = trimesh.creation.box(extents=(27.0, 6.0, 16.0))
        rotation = trimesh.transformations.rotation_matrix(np.deg2rad(angle), (0, 0, 1))[:3, :3]
        parts.append(placed(rib, rotation, (*polar(angle, 28.5), 14.0)))
    return trimesh.util.concatenate(parts)


def _bent_bracket() -> trimesh.Trimesh:
    """Base plate and a narrower upright at one edge, holes off-centre, one corner chamfered: no symmetry."""
    base_outline = np.array([(0, 0), (72, 0), (72, 34), (60, 46), (0, 46)], dtype=np.float64)
    base_holes = [circle(4.5, (50.0, 14.0)), circle(3.0, (30.0, 34.0)), circle(3.0, (62.0, 30.0))]
    upright_outline = np.array([(0, 0), (30, 0), (30, 40), (22, 52), (0, 52)], dtype=np.float64)  # (y, z)
    upright = slab(upright_outline, [circle(5.0, (14.0, 36.0))], 6.0)
    uv_w_to_xyz = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # outline (u, v) -> (y, z), w -> x
    return trimesh.util.concatenate([slab(base_outline, base_holes, 6.0), placed(upright, uv_w_to_xyz, (0, 0, 0))])


def _stepped_shaft() -> trimesh.Trimesh:
    """Shaft with a collar, two journals of different diameter and a thin spigot: continuous about z, no flip."""
    return revolve([(0, 0), (6, 0), (7, 1), (7, 28), (17, 28), (17, 36), (13, 36), (13, 80), (11, 82), (11, 96),
                     (8, 96), (7, 110), (0, 110)])


def _square_flange_with_chamfer() -> trimesh.Trimesh:
    """Square flange with a tube, a bore and four corner holes; the corner at +x +y is chamfered, which breaks
    the 4-fold symmetry it otherwise has."""
    chamfer = 13.0
    outline = np.array([(-35, -35), (35, -35), (35, 35 - chamfer), (35 - chamfer, 35), (-35, 35)], dtype=np.float64)
    holes = [circle(12.0)] + [circle(4.0, (x, y)) for x in (-22.0, 22.0) for y in (-22.0, 22.0)]
    return trimesh.util.concatenate([slab(outline, holes, 8.0), slab(circle(19.0), [circle(12.0)], 26.0, 4.0)])


def _connecting_rod() -> trimesh.Trimesh:
    """Flat tapered link between a big and a small eye, a thick boss round the big eye on both faces: 2-fold
    about the long axis x only (the boss and the eyes tell the ends apart)."""
    ends = np.concatenate([circle(16.0, (-40.0, 0.0)), circle(11.0, (40.0, 0.0))])
    outline = ends[ConvexHull(ends).vertices]
    link = slab(outline, [circle(8.0, (-40.0, 0.0)), circle(4.5, (40.0, 0.0))], 8.0, z0_mm=-4.0)
    boss = slab(circle(17.0, (-40.0, 0.0)), [circle(8.0, (-40.0, 0.0))], 20.0, z0_mm=-10.0)
    return trimesh.util.concatenate([link, boss])


def _l_plate() -> trimesh.Trimesh:
    """L-shaped plate, legs 84 and 58 mm long and 26 and 34 mm wide, a bored boss at the corner on the top face,
    a 7 mm and a 4 mm hole at uneven places along the legs: no symmetry."""
    outline = np.array([(0, 0), (84, 0), (84, 26), (34, 26), (34, 58), (0, 58)], dtype=np.float64)
    holes = [circle(3.5, (66.0, 12.0)), circle(2.0, (16.0, 46.0)), circle(5.0, (16.0, 14.0))]
    boss = slab(circle(11.0, (16.0, 14.0)), [circle(5.0, (16.0, 14.0))], 14.0, z0_mm=4.0)
    return trimesh.util.concatenate([slab(outline, holes, 8.0), boss])


def _dog_bone_link() -> trimesh.Trimesh:
    """Flat link of two round ends joined by a narrower waist, a hub round each end hole on the top face; the
    hole at +x is 14 mm across, the one at -x 7 mm, which breaks the 2-fold symmetry about z it otherwise has."""
    ends = [(-34.0, 0.0), (34.0, 0.0)]
    arc = [polar(angle, 16.0) for angle in np.linspace(-120.0, 120.0, 33)]  # an end's outline about its centre
    waist = [(18.0, 8.0), (-18.0, 8.0)]  # the top edge of the waist, +x to -x
    outline = [(34.0 + x, y) for x, y in arc] + waist + [(-34.0 - x, -y) for x, y in arc] + [(-x, -y) for x, y in waist]
    holes = [circle(3.5, ends[0]), circle(7.0, ends[1])]
    hubs = [slab(circle(12.0, end), [hole], 10.0, z0_mm=4.0) for end, hole in zip(ends, holes, strict=True)]
    return trimesh.util.concatenate([slab(np.array(outline), holes, 8.0), *hubs])


def _hex_flange() -> trimesh.Trimesh:
    """Hexagon plate (36 mm from centre to corner, corners on x) with a bore and six bolt holes between the
    corners, a round boss on the top face: 6-fold about z, no flip."""
    outline = np.array([polar(60.0 * k, 36.0) for k in range(6)])
    holes = [circle(9.0)] + [circle(3.5, polar(60.0 * k + 30.0, 24.0)) for k in range(6)]
    return trimesh.util.concatenate([slab(outline, holes, 9.0), slab(circle(16.0), [circle(9.0)], 18.0, z0_mm=5.0)])


def _window_frame() -> trimesh.Trimesh:
    """Rectangular frame 92 x 60 mm with a centred 44 x 22 mm window and a hole near each corner, 10 mm thick:
    2-fold about x, y and z."""
    outline = np.array([(-46, -30), (46, -30), (46, 30), (-46, 30)], dtype=np.float64)
    window = np.array([(-22, -11), (22, -11), (22, 11), (-22, 11)], dtype=np.float64)
    holes = [window] + [circle(4.5, (x, y)) for x in (-36.0, 36.0) for y in (-20.0, 20.0)]
    return slab(outline, holes, 10.0)


@dataclass(frozen=True)
class OwnPart:
    """One part of our own (a validation or a tuning part): how to build it (mm), its symmetries (BOP
    ``models_info`` keys), and whether it nearly has a symmetry it does not declare (the near-symmetry finder must
    report it)."""

    obj_id: int
    name: str
    build: Callable[[], trimesh.Trimesh]
    symmetries: dict[str, Any]
    near_symmetric: bool = False


VALIDATION_PARTS: tuple[OwnPart, ...] = (
    OwnPart(1, "gear_12", _gear_12, {"symmetries_discrete": about_z(12) + flips(12)}),
    OwnPart(2, "three_rib_flange", _three_rib_flange, {"symmetries_discrete": about_z(3)}),
    OwnPart(3, "bent_bracket", _bent_bracket, {}),
    OwnPart(4, "stepped_shaft", _stepped_shaft, {"symmetries_continuous": [Z_AXIS]}),
    OwnPart(5, "square_flange_with_chamfer", _square_flange_with_chamfer, {}, near_symmetric=True),
    OwnPart(6, "connecting_rod", _connecting_rod, {"symmetries_discrete": [rotation_4x4((1, 0, 0), np.pi)]}),
)

TUNING_PARTS: tuple[OwnPart, ...] = (
    OwnPart(1, "l_plate", _l_plate, {}),
    OwnPart(2, "dog_bone_link", _dog_bone_link, {}, near_symmetric=True),
    OwnPart(3, "hex_flange", _hex_flange, {"symmetries_discrete": about_z(6)}),
    OwnPart(4, "window_frame", _window_frame,
            {"symmetries_discrete": flips(2) + [rotation_4x4((0, 0, 1), np.pi)]}),
)


def build_own_part(part: OwnPart) -> trimesh.Trimesh:
    """The mesh (mm) of one of our own parts, centred on its bounding box."""
    mesh = part.build()
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def write_models(parts: Sequence[OwnPart], out_dir: str | Path) -> Path:
    """Write each of ``parts`` as ``obj_XXXXXX.ply`` plus ``models_info.json`` (the built-in parts' format,
    ``popcode_trainer.data.objects.write_builtin_models``); returns the folder."""
    return write_models_folder({part.obj_id: (build_own_part(part), part.symmetries) for part in parts}, out_dir)


PART_SETS = {"validation": VALIDATION_PARTS, "tuning": TUNING_PARTS}


def main(argv: Sequence[str] | None = None) -> Path:
    """``SET --out DIR``: write the part set ``SET`` into the models folder ``DIR``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("part_set", choices=list(PART_SETS), help="which set of parts to write")
    parser.add_argument("--out", type=Path, required=True, help="models folder to write (created if missing)")
    args = parser.parse_args(argv)
    parts = PART_SETS[args.part_set]
    out_dir = write_models(parts, args.out)
    for part in parts:
        print(f"obj_{part.obj_id:06d}.ply  {part.name}")
    print(f"wrote {len(parts)} {args.part_set} parts and models_info.json to {out_dir}")
    return out_dir


if __name__ == "__main__":
    run_command("tools.own_parts", main)
