"""Issue 50: a models folder's counts are bounded before the work they size, and its declarations are checked."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import cdist

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.limits import MAX_DISCRETE_SYMMETRIES
from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_trainer.data import meshes, symmetry_check
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.data.meshes import MAX_MESH_BYTES, load_mesh
from popcode_trainer.data.objects import BUILTIN_PARTS, build_part, mesh_diameter_mm, model_info
from popcode_trainer.data.symmetry_check import check_closed

_HEADER = "ply\nformat {form} 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n" \
          "element face {faces}\nproperty list uchar int vertex_indices\nend_header\n"


def _about_z(turns: int, of: int) -> list[list[float]]:
    """``symmetries_discrete``: the rotations by k/of of a turn about z, k = 1 .. turns."""
    result = []
    for k in range(1, turns + 1):
        matrix = np.eye(4)
        matrix[:3, :3] = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), 2 * np.pi * k / of)
        result.append(matrix.ravel().tolist())
    return result


def _largest_distance(points: np.ndarray) -> float:
    """The BOP toolkit's diameter: the largest distance between two of the points, every pair measured."""
    return float(max(cdist(points[i:i + 512], points).max() for i in range(0, len(points), 512)))


def test_a_mesh_is_bounded_before_it_is_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A PLY header's counts and a file's size are refused before trimesh sizes anything by them."""
    def read(*args: object, **kwargs: object) -> None:
        raise AssertionError("the mesh was read before its bounds were checked")

    cases = {
        "billions.ply": (_HEADER.format(form="ascii", vertices=3_000_000_000, faces=1) + "0 0 0\n3 0 0 0\n",
                         "its header claims 3,000,000,000 vertex elements; at most 4,000,000 are allowed"),
        "faces.ply": (_HEADER.format(form="binary_little_endian", vertices=3, faces=5_000_000),
                      "its header claims 5,000,000 face elements; at most 4,000,000"),
        "truncated.ply": (_HEADER.format(form="binary_little_endian", vertices=1000, faces=10) + "x" * 100,
                          "its header claims 1,000 vertex, 10 face elements, more than its 100 bytes of data hold"),
        "endless_header.ply": ("ply\nformat ascii 1.0\n" + "comment\n" * 2000, "no end_header within 1000 lines"),
    }
    for name, (text, _) in cases.items():
        (tmp_path / name).write_text(text)
    huge = tmp_path / "huge.ply"
    with huge.open("wb") as handle:
        handle.truncate(MAX_MESH_BYTES + 1)  # sparse: no disk is written
    monkeypatch.setattr(meshes.trimesh, "load", read)
    with pytest.raises(PopcodeError, match="holds 536,870,913 bytes; at most 536,870,912 are allowed: decimate"):
        load_mesh(huge)
    for name, (_, expect) in cases.items():
        with pytest.raises(PopcodeError, match=expect):
            load_mesh(tmp_path / name)


def test_a_mesh_without_a_header_is_counted_once_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    box = trimesh.creation.box((10.0, 20.0, 30.0))
    for name in ("box.ply", "box_ascii.ply", "box.obj"):
        box.export(tmp_path / name, **({"encoding": "ascii"} if "ascii" in name else {}))
        assert len(load_mesh(tmp_path / name).faces) == 12
    monkeypatch.setattr(meshes, "MAX_MESH_ELEMENTS", 10)
    with pytest.raises(PopcodeError, match=r"box.obj has \d+ vertices and 12 faces; at most 10 of each are allowed"):
        load_mesh(tmp_path / "box.obj")
    with pytest.raises(PopcodeError, match="its header claims 12 face elements; at most 10"):
        load_mesh(tmp_path / "box.ply")


def test_the_diameter_is_the_largest_vertex_distance_at_bounded_cost() -> None:
    """Every pair up to 4096 vertices (the built-in parts' diameters as the BOP toolkit measures them, to the last
    digit); beyond, among the extremes along many directions, at most 0.15 % short."""
    for part in BUILTIN_PARTS:
        mesh = build_part(part.obj_id)
        assert mesh_diameter_mm(mesh) == _largest_distance(np.asarray(mesh.vertices)) == \
            model_info(mesh, {})["diameter"], part.name
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=50.0)  # 10242 vertices, all on the hull
    assert len(sphere.vertices) > 4096
    assert 100.0 * (1 - 0.0015) <= mesh_diameter_mm(sphere) <= 100.0 + 1e-9


def _models(folder: Path, **entry: object) -> Path:
    folder.mkdir()
    bar = trimesh.creation.box((60.0, 30.0, 10.0))
    bar.export(folder / "obj_000001.ply")
    (folder / "models_info.json").write_text(json.dumps({"1": {**model_info(bar, {}), **entry}}))
    return folder


@pytest.mark.parametrize(("entry", "expect"), [
    ({"diameter": "71"}, "key 'diameter' of object 1 must be a positive number, got '71' (str); its mesh's diameter "
                         "is 67.8233 mm (the largest distance between two of its vertices: "
                         "popcode_trainer.data.objects.model_info writes it)"),
    ({"diameter": False}, "got False (bool); its mesh's diameter is 67.8233 mm"),
    ({"diameter": 0}, "got 0 (int); its mesh's diameter is 67.8233 mm"),
    ({"size_y": "30"}, "models_info.json: object 1: size_y must be a number, got '30' (str)"),
    ({"min_x": [-30]}, "object 1: min_x must be a number"),
    ({"symmetries_discrete": [[str(v) for v in np.eye(4).ravel()]]}, "symmetries_discrete[0] is not a list of"),
    ({"symmetries_continuous": [{"axis": [0, 0, True]}]}, "symmetries_continuous[0] axis is not a list of numbers"),
], ids=["diameter-text", "diameter-false", "diameter-zero", "size-text", "min-list", "matrix-text", "axis-true"])
def test_every_number_of_models_info_is_a_number(entry: dict, expect: str, tmp_path: Path) -> None:
    with pytest.raises(PopcodeError) as error:
        load_models_info(_models(tmp_path / "models", **entry))
    assert expect in str(error.value)


def test_objects_are_counted_before_any_is_read(tmp_path: Path) -> None:
    folder = tmp_path / "models"
    folder.mkdir()
    (folder / "models_info.json").write_text(json.dumps({str(k): "not an entry" for k in range(1, 10_002)}))
    with pytest.raises(PopcodeError, match="lists 10001 objects; at most 10000 are allowed"):
        load_models_info(folder)


def test_repeats_are_refused_and_a_group_at_the_limit_closes() -> None:
    """The closure is vectorised: a group of 1001 (the identity and 1000 listed) is checked in seconds; one listed
    short of a group names what it lacks, and a set that generates more than can be listed is refused."""
    assert symmetry_check.MAX_GROUP == MAX_DISCRETE_SYMMETRIES + 1
    with pytest.raises(PopcodeError, match=r"bar: symmetries_discrete\[2\] \(rotation 180.0 deg about \(0, 0, 1\)\) "
                                           r"repeats symmetries_discrete\[1\]; list each symmetry once"):
        check_closed({"symmetries_discrete": _about_z(2, 4) + _about_z(1, 2)}, "bar", 100.0)
    with pytest.raises(PopcodeError, match=r"symmetries_discrete\[0\] \(rotation 0.0 deg .*repeats the identity"):
        check_closed({"symmetries_discrete": [np.eye(4).ravel().tolist()]}, "bar", 100.0)
    check_closed({"symmetries_discrete": _about_z(MAX_DISCRETE_SYMMETRIES, MAX_DISCRETE_SYMMETRIES + 1)}, "gear", 100.0)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # a half turn about x
    dihedral = _about_z(11, 12) + [(flip @ np.asarray(turn).reshape(4, 4)).ravel().tolist()
                                   for turn in [np.eye(4).ravel().tolist(), *_about_z(11, 12)]]
    check_closed({"symmetries_discrete": dihedral}, "gear", 100.0)
    with pytest.raises(PopcodeError, match="not closed under composition: .* lacks 1 in all; declare all 23 "):
        check_closed({"symmetries_discrete": dihedral[:-1]}, "gear", 100.0)
    skew = [np.block([[axis_angle_to_matrix(np.array(axis), 1.0), np.zeros((3, 1))], [np.zeros((1, 3)), 1.0]])
            .ravel().tolist() for axis in ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0))]
    with pytest.raises(PopcodeError, match="generate more than 1000 transforms besides the identity"):
        check_closed({"symmetries_discrete": skew}, "skew", 100.0)
