"""Four parts of our own to choose recipe settings on, so that the validation parts stay parts no choice was tuned on.

    python -m bench.tuning_parts --out DIR

writes a BOP models folder (``obj_000001.ply`` ... ``obj_000004.ply`` and ``models_info.json``, millimetres,
each mesh centred on its bounding box) as ``python -m bench.validation_parts`` does. A recipe setting (code size,
sigma, epochs, augmentation) is chosen on these parts; the chosen recipe is then judged once on the validation
parts (``bench/validation_parts.py``), never tuned on them, so their score says how the recipe does on parts it
has not seen. The tuning parts have the same kinds of difficulty as the validation ones, in other shapes than
those and the built-in parts (``popcode_trainer.data.objects``):

1. an L-shaped plate with unequal legs, a boss at the corner and two holes of different sizes: no symmetry,
2. a dog-bone link with a hub round each end hole on one face, one hole wider than the other: it looks
   2-fold about z, but the holes tell the ends apart, so it declares nothing (the near-symmetry warning,
   ``popcode_trainer.data.near_symmetry``, reports it: a recipe meets look-alike poses here),
3. a hexagon flange with a bore, six bolt holes and a round boss on one face: 6-fold about z, no flip,
4. a rectangular frame with a centred window and four corner holes: 2-fold about x, y and z (dihedral group
   D2, 4 poses).

They are built with the helpers of ``bench/validation_parts.py`` (each circle's vertices map onto themselves under
the part's rotations, so each declared symmetry holds to rounding); ``tests/bench/test_own_part_sets.py`` checks
them with the symmetry check and the near-symmetry finder, and that ``popcode-train demo --objects DIR`` accepts
the folder.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from bench.command import run_command
from bench.validation_parts import OwnPart, about_z, circle, flips, polar, slab, write_models_main
from popcode_trainer.data.objects import rotation_4x4


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


TUNING_PARTS: tuple[OwnPart, ...] = (
    OwnPart(1, "l_plate", _l_plate, {}),
    OwnPart(2, "dog_bone_link", _dog_bone_link, {}, near_symmetric=True),
    OwnPart(3, "hex_flange", _hex_flange, {"symmetries_discrete": about_z(6)}),
    OwnPart(4, "window_frame", _window_frame,
            {"symmetries_discrete": flips(2) + [rotation_4x4((0, 0, 1), np.pi)]}),
)


def main(argv: Sequence[str] | None = None) -> Path:
    return write_models_main(TUNING_PARTS, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    run_command("tuning_parts", main)
