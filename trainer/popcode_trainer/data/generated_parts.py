"""CAD-like parts drawn at random, with their exact symmetries, for pretraining a trunk on many parts (issue 53).

A network that has seen many parts starts a user's parts with edges, shading and small features already learnt.
The parts come from these families, each drawn with random dimensions and feature counts:

- **bolted plates**: a regular polygon or a round rim with a bore and a ring of bolt holes; n-fold about z and, with
  both faces alike, the n flips about in-plane axes (dihedral group); a hub on one face keeps the n turns alone;
- **pinned bodies**: a random revolved profile with a ring of radial pins (n-fold about z), or without them
  (continuous symmetry about z);
- **channels**: a base plate with two walls and holes, 2-fold about z;
- **brackets** (an L of two plates with holes at random places) and **ribbed blocks** (bosses and ribs at random
  places): no symmetry;
- **look-alikes**: a plate, body or channel that would be symmetric but for one small feature (a pin, a tab, a
  longer pin), declared without symmetry -- the parts whose small feature a network must learn to see.

Every circle has a vertex count that the part's rotations map onto itself and every repeated feature is the first
one turned by the declared rotation, so each declaration holds to rounding; the symmetry check
(:mod:`.symmetry_check`) passes them (``tests/trainer/test_generated_parts.py``). Each part is centred on its
symmetry axis (the z axis) and on its bounding box along the rest. The families share no generator with the
built-in parts (:mod:`.objects`) or the project's tuning and validation parts (``tools.own_parts``), and their
random dimensions make a part equal to one of those only by chance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json, write_json_atomic

from .objects import Z_AXIS, revolve, write_models_folder
from .solids import CIRCLE_SECTIONS, TriangulationError, about_z, circle, flips, placed, polar, slab

KINDS = ("discrete", "none", "look_alike", "continuous")
# The share of each kind among generated parts when all four are asked for (the continuous ones train on their own
# axis-only code, so a pretraining that uses the full code asks for the other three).
KIND_WEIGHTS = {"discrete": 0.35, "none": 0.25, "look_alike": 0.25, "continuous": 0.15}
ORDERS = (2, 3, 4, 6, 8)  # n of n-fold parts: the 96-vertex rims and 48-vertex circles hold each of them exactly
MAX_PARTS = 10_000
GENERATED_LIST = "generated_parts.json"  # beside models_info.json: each part's family and kind
MIN_WEB_MM = 3.5  # material between two holes, or a hole and an edge (the plates' outline is kept where >= 3 mm)
DRAWS = 50  # a part whose random dimensions leave no room for its features is drawn again, at most this often


@dataclass(frozen=True)
class GeneratedPart:
    """One generated part: its mesh (mm, centred), BOP symmetries and what it is."""

    obj_id: int
    family: str
    kind: str  # one of KINDS
    mesh: trimesh.Trimesh
    symmetries: dict[str, Any]


class _NoRoomError(Exception):
    """The dimensions drawn leave no room for a feature: draw the part again."""


def _sections(order: int, at_least: int = CIRCLE_SECTIONS) -> int:
    """A vertex count of at least ``at_least`` that ``order`` divides."""
    return order * int(np.ceil(at_least / order))


def _turned(mesh: trimesh.Trimesh, order: int) -> list[trimesh.Trimesh]:
    """``mesh`` and its ``order - 1`` copies turned about z by multiples of ``360 / order`` deg."""
    return [placed(mesh.copy(), trimesh.transformations.rotation_matrix(2 * np.pi * k / order, (0, 0, 1))[:3, :3],
                   (0.0, 0.0, 0.0)) for k in range(order)]


def _bolted_plate(rng: np.random.Generator, order: int, look_alike: bool) -> tuple[list[trimesh.Trimesh], bool]:
    """A plate with a bore and ``order`` bolt holes (polygon outline for even orders, else round); returns the solids
    and whether both faces are alike (then the flips hold too)."""
    radius = rng.uniform(24.0, 55.0)
    thickness = rng.uniform(5.0, 14.0)
    offset = 180.0 / order if rng.random() < 0.5 else 0.0  # between the corners or at them: on a mirror line either way
    if order % 2 == 0 and order > 2 and rng.random() < 0.5:
        outline = np.array([polar(360.0 * k / order, radius) for k in range(order)])
        inscribed = radius * np.cos(np.pi / order)
    elif order == 2:
        outline = np.array([(-radius, -0.55 * radius), (radius, -0.55 * radius), (radius, 0.55 * radius),
                            (-radius, 0.55 * radius)])
        inscribed, offset = 0.55 * radius, 0.0  # the holes along the long axis x, where they fit
    else:
        outline = circle(radius, sections=_sections(order, 96))
        inscribed = radius * np.cos(np.pi / _sections(order, 96))
    hole_radius_at = inscribed * rng.uniform(0.55, 0.75) if order > 2 else radius * rng.uniform(0.55, 0.75)
    room = inscribed if order > 2 else radius  # from the centre to the outline along the holes' direction
    bore = min(radius * rng.uniform(0.12, 0.3), 0.8 * hole_radius_at - 4.0)
    # a bolt hole keeps MIN_WEB_MM from the bore, the outline and its neighbours
    neighbours = 2.0 * hole_radius_at * np.sin(np.pi / order) if order > 1 else np.inf
    bolt = min(rng.uniform(0.06, 0.13) * radius, hole_radius_at - bore - MIN_WEB_MM, room - hole_radius_at - MIN_WEB_MM,
               (neighbours - MIN_WEB_MM) / 2)
    if bolt < 1.5 or bore < 2.0:
        raise _NoRoomError("no room for the holes")
    sections = _sections(order)
    holes = [circle(bore, sections=sections)] + [circle(bolt, polar(360.0 * k / order + offset, hole_radius_at),
                                                        sections=sections) for k in range(order)]
    solids = [slab(outline, holes, thickness)]
    alike_faces = rng.random() < 0.4
    if not alike_faces:
        hub = bore + rng.uniform(0.15, 0.4) * (hole_radius_at - bore)
        solids.append(slab(circle(hub, sections=sections), [circle(bore, sections=sections)],
                           rng.uniform(0.6, 2.0) * thickness, z0_mm=thickness))
    if look_alike:  # a small pin on the top face beside one bolt hole
        pin = trimesh.creation.cylinder(radius=max(2.0, 0.5 * bolt), height=rng.uniform(0.5, 1.2) * thickness,
                                        sections=24)
        at = polar(offset + 180.0 / order, hole_radius_at)
        solids.append(placed(pin, np.eye(3), (*at, thickness + pin.extents[2] / 2 - 0.5)))
    return solids, alike_faces and not look_alike


def _profile(rng: np.random.Generator) -> tuple[list[tuple[float, float]], float]:
    """A random stepped (r, z) profile from the axis to the axis; returns it and its largest radius."""
    steps = int(rng.integers(2, 5))
    height = rng.uniform(30.0, 100.0)
    radii = rng.uniform(8.0, 35.0, size=steps)
    cuts = np.sort(rng.uniform(0.0, height, size=steps - 1))
    levels = np.concatenate([[0.0], cuts, [height]])
    profile = [(0.0, 0.0)]
    for radius, (low, high) in zip(radii, zip(levels[:-1], levels[1:], strict=True), strict=True):
        profile += [(float(radius), float(low)), (float(radius), float(high))]
    profile.append((0.0, height))
    # neighbouring steps meet at a level: drop zero-length segments revolve would turn into degenerate faces
    cleaned = [point for index, point in enumerate(profile) if index == 0 or point != profile[index - 1]]
    return cleaned, float(radii.max())


def _pinned_body(rng: np.random.Generator, order: int, look_alike: bool) -> list[trimesh.Trimesh]:
    """A revolved body with ``order`` radial pins at one level (none: ``order`` 0)."""
    profile, widest = _profile(rng)
    body = revolve(profile)
    if order == 0:
        return [body]
    level = rng.uniform(0.2, 0.8) * profile[-1][1]
    inner = float(max(r for r, z in profile[1:-1]))
    length = rng.uniform(0.3, 0.8) * widest + 4.0
    pin_radius = rng.uniform(2.5, 6.0)
    pin = trimesh.creation.cylinder(radius=pin_radius, height=inner + length, sections=CIRCLE_SECTIONS)
    pin = placed(pin, trimesh.geometry.align_vectors((0, 0, 1), (1, 0, 0))[:3, :3],
                 ((inner + length) / 2, 0.0, level))
    solids = [body, *_turned(pin, order)]
    if look_alike:  # one pin longer than the others
        extra = trimesh.creation.cylinder(radius=pin_radius * 0.7, height=rng.uniform(0.15, 0.3) * length + 3.0,
                                          sections=24)
        solids.append(placed(extra, trimesh.geometry.align_vectors((0, 0, 1), (1, 0, 0))[:3, :3],
                             (inner + length + extra.extents[2] / 2 - 0.5, 0.0, level)))
    return solids


def _channel(rng: np.random.Generator, look_alike: bool) -> list[trimesh.Trimesh]:
    """A base plate with a wall along each long edge and holes placed in pairs: 2-fold about z."""
    length, width = rng.uniform(40.0, 110.0), rng.uniform(24.0, 50.0)
    base, wall, height = rng.uniform(4.0, 9.0), rng.uniform(4.0, 8.0), rng.uniform(12.0, 35.0)
    outline = np.array([(-length / 2, -width / 2), (length / 2, -width / 2), (length / 2, width / 2),
                        (-length / 2, width / 2)])
    pairs = int(rng.integers(1, 3))
    spacing = length / (2 * pairs + 1)
    hole = min(rng.uniform(2.5, 6.0), 0.3 * (width / 2 - wall), 0.3 * spacing)
    centres = [(spacing * (k + 1), rng.uniform(-0.15, 0.15) * width) for k in range(pairs)]
    holes = [circle(hole, (x, y)) for x, y in centres] + [circle(hole, (-x, -y)) for x, y in centres]
    solids = [slab(outline, holes, base)]
    wall_box = trimesh.creation.box(extents=(length, wall, height))
    solids += [placed(wall_box.copy(), np.eye(3), (0.0, side * (width / 2 - wall / 2), base + height / 2))
               for side in (-1, 1)]
    if look_alike:  # a tab on one end of one wall
        tab = trimesh.creation.box(extents=(rng.uniform(6.0, 12.0), wall, rng.uniform(5.0, 10.0)))
        solids.append(placed(tab, np.eye(3), (length / 2 - tab.extents[0] / 2, width / 2 - wall / 2,
                                              base + height + tab.extents[2] / 2 - 0.5)))
    return solids


def _bracket(rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """An L of a base plate and an upright of other sizes, holes at random places: no symmetry."""
    length, width, base = rng.uniform(40.0, 90.0), rng.uniform(25.0, 55.0), rng.uniform(4.0, 9.0)
    outline = np.array([(0.0, 0.0), (length, 0.0), (length, width), (0.0, width)])
    cut = rng.uniform(0.1, 0.3) * min(length, width)
    outline[2] = (length - cut, width)  # one corner chamfered
    outline = np.insert(outline, 2, (length, width - cut), axis=0)
    holes = [circle(rng.uniform(2.5, 5.0), (rng.uniform(0.3, 0.75) * length, rng.uniform(0.25, 0.6) * width))]
    upright_height = rng.uniform(25.0, 70.0)
    upright = slab(np.array([(0.0, 0.0), (width, 0.0), (width, upright_height), (0.0, upright_height)]),
                   [circle(rng.uniform(2.5, 5.0), (rng.uniform(0.3, 0.7) * width, rng.uniform(0.5, 0.8)
                                                    * upright_height))], base)
    uv_w_to_xyz = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # outline (u, v) -> (y, z), w -> x
    return [slab(outline, holes, base), placed(upright, uv_w_to_xyz, (0.0, 0.0, 0.0))]


def _ribbed_block(rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """A block with bosses and ribs at random places on its top and one side: no symmetry."""
    size = np.array([rng.uniform(30.0, 90.0), rng.uniform(20.0, 60.0), rng.uniform(10.0, 30.0)])
    solids = [trimesh.creation.box(extents=size)]
    for _ in range(int(rng.integers(2, 5))):
        x, y = rng.uniform(-0.4, 0.4) * size[0], rng.uniform(-0.4, 0.4) * size[1]
        if rng.random() < 0.5:
            boss = trimesh.creation.cylinder(radius=rng.uniform(3.0, 0.25 * size[1] + 3.0),
                                             height=rng.uniform(5.0, 20.0), sections=CIRCLE_SECTIONS)
        else:
            boss = trimesh.creation.box(extents=(rng.uniform(4.0, 0.6 * size[0]), rng.uniform(3.0, 8.0),
                                                 rng.uniform(5.0, 20.0)))
        solids.append(placed(boss, np.eye(3), (x, y, size[2] / 2 + boss.extents[2] / 2 - 0.5)))
    rib = trimesh.creation.box(extents=(rng.uniform(0.3, 0.8) * size[0], rng.uniform(4.0, 12.0), rng.uniform(3.0, 8.0)))
    solids.append(placed(rib, np.eye(3), (rng.uniform(-0.2, 0.2) * size[0], -size[1] / 2 - rib.extents[1] / 2 + 0.5,
                                          rng.uniform(-0.2, 0.2) * size[2])))
    return solids


def _part(rng: np.random.Generator, kind: str) -> tuple[str, list[trimesh.Trimesh], dict[str, Any]]:
    """The family, solids and symmetries of one part of ``kind``."""
    if kind == "continuous":
        return "pinned_body", _pinned_body(rng, 0, False), {"symmetries_continuous": [Z_AXIS]}
    if kind == "none":
        if rng.random() < 0.5:
            return "bracket", _bracket(rng), {}
        return "ribbed_block", _ribbed_block(rng), {}
    look_alike = kind == "look_alike"
    family = str(rng.choice(["bolted_plate", "pinned_body", "channel"], p=[0.5, 0.3, 0.2]))
    order = int(rng.choice(ORDERS))
    if family == "channel":
        solids, symmetries = _channel(rng, look_alike), {"symmetries_discrete": about_z(2)}
    elif family == "pinned_body":
        solids, symmetries = _pinned_body(rng, order, look_alike), {"symmetries_discrete": about_z(order)}
    else:
        solids, alike_faces = _bolted_plate(rng, order, look_alike)
        symmetries = {"symmetries_discrete": about_z(order) + (flips(order) if alike_faces else [])}
    return family, solids, {} if look_alike else symmetries


def _drawn(rng: np.random.Generator, kind: str) -> tuple[str, list[trimesh.Trimesh], dict[str, Any]]:
    """:func:`_part`, drawn again while its dimensions leave no room for its features."""
    for _ in range(DRAWS):
        try:
            return _part(rng, kind)
        except (_NoRoomError, TriangulationError):
            continue
    raise PopcodeError(f"no {kind} part fitted its features in {DRAWS} draws")  # a generator bug: never seen


def _centred(solids: Sequence[trimesh.Trimesh], on_z_axis: bool) -> trimesh.Trimesh:
    """The solids as one mesh, moved so its bounding box is centred (along z only when it turns about z)."""
    mesh = trimesh.util.concatenate(list(solids))
    centre = mesh.bounds.mean(axis=0)
    if on_z_axis:
        centre[:2] = 0.0
    mesh.apply_translation(-centre)
    return mesh


def generate_parts(count: int, seed: int, kinds: Sequence[str] = KINDS, first_id: int = 1) -> list[GeneratedPart]:
    """``count`` parts drawn with ``seed`` among ``kinds`` (in :data:`KIND_WEIGHTS` proportions), ids from
    ``first_id``; the same arguments give the same parts."""
    if not 1 <= count <= MAX_PARTS:
        raise PopcodeError(f"the number of generated parts must lie in [1, {MAX_PARTS}], got {count}")
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown or not kinds:
        raise PopcodeError(f"unknown part kinds {unknown or 'none given'}; choose among {list(KINDS)}")
    weights = np.array([KIND_WEIGHTS[kind] for kind in kinds])
    parts = []
    for index in range(count):
        rng = np.random.default_rng([seed, index])
        kind = str(rng.choice(list(kinds), p=weights / weights.sum()))
        family, solids, symmetries = _drawn(rng, kind)
        mesh = _centred(solids, on_z_axis=family in ("bolted_plate", "pinned_body", "channel"))
        parts.append(GeneratedPart(first_id + index, family, kind, mesh, symmetries))
    return parts


def write_generated_models(parts: Sequence[GeneratedPart], out_dir: str | Path) -> Path:
    """Each part as ``obj_XXXXXX.ply`` plus ``models_info.json`` (a BOP models folder that ``render`` and ``demo
    --objects`` read) and :data:`GENERATED_LIST` (family and kind of each); returns the folder."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_dir / GENERATED_LIST, {str(p.obj_id): {"family": p.family, "kind": p.kind} for p in parts})
    return write_models_folder({p.obj_id: (p.mesh, p.symmetries) for p in parts}, out_dir)


def kinds_of(models_dir: Path) -> dict[int, str]:
    """The kind of each generated part of a folder :func:`write_generated_models` wrote."""
    listing = read_json(models_dir / GENERATED_LIST)
    return {int(obj_id): str(entry["kind"]) for obj_id, entry in listing.items()}

