"""Declared symmetries are checked against the mesh: real ones pass, wrong or incomplete ones are named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_trainer.data import symmetry_check
from popcode_trainer.data.hull import with_hull_points
from popcode_trainer.data.objects import BUILTIN_PARTS, build_part, model_info
from popcode_trainer.data.symmetry_check import check_models_symmetries, check_object_symmetries, check_symmetries


def _flat(axis: tuple[float, float, float], angle_deg: float, t_mm: tuple[float, float, float] = (0, 0, 0)) -> list:
    """Row-major 4x4 of ``x -> R x + t`` (BOP ``symmetries_discrete``)."""
    matrix = np.eye(4)
    matrix[:3, :3] = axis_angle_to_matrix(np.asarray(axis, float), np.deg2rad(angle_deg))
    matrix[:3, 3] = t_mm
    return matrix.ravel().tolist()


def _about_z(order: int) -> list:
    return [_flat((0, 0, 1), 360.0 * k / order) for k in range(1, order)]


def _bar() -> trimesh.Trimesh:
    """60 x 30 x 10 mm box: 2-fold about x, y and z, not 4-fold."""
    return trimesh.creation.box((60.0, 30.0, 10.0))


def _square() -> trimesh.Trimesh:
    return trimesh.creation.box((40.0, 40.0, 10.0))


def _dodecagon() -> trimesh.Trimesh:
    """A 12-sided prism: 12-fold about z."""
    return trimesh.creation.cylinder(radius=30.0, height=10.0, sections=12)


def _rod() -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=10.0, height=60.0, sections=96)


def _info(mesh: trimesh.Trimesh, **symmetries: list) -> dict:
    return model_info(mesh, symmetries)


@pytest.mark.parametrize(("mesh", "symmetries"), [
    (_bar(), {"symmetries_discrete": _about_z(2)}),
    (_bar(), {"symmetries_discrete": [_flat(axis, 180) for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]}),
    (_square(), {"symmetries_discrete": _about_z(4)}),
    (_dodecagon(), {"symmetries_discrete": _about_z(12)}),
    (_rod(), {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}),
    # flips about x and y compose to a half-turn about z, which the continuous symmetry covers
    (_rod(), {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
              "symmetries_discrete": [_flat((1, 0, 0), 180), _flat((0, 1, 0), 180)]}),
], ids=["2-fold", "three-2-folds", "4-fold", "12-fold", "continuous", "continuous-flips"])
def test_real_symmetries_pass(mesh: trimesh.Trimesh, symmetries: dict) -> None:
    check_symmetries(mesh, _info(mesh, **symmetries), "part")


def test_symmetries_off_the_origin_pass() -> None:
    """A part whose origin is not its centre: the declared translations (mm) and offset carry it."""
    bar, rod = _bar(), _rod()
    bar.apply_translation((100.0, 0.0, 0.0))
    rod.apply_translation((5.0, -7.0, 0.0))
    check_symmetries(bar, _info(bar, symmetries_discrete=[_flat((0, 0, 1), 180, (200.0, 0.0, 0.0))]), "bar")
    check_symmetries(rod, _info(rod, symmetries_continuous=[{"axis": [0, 0, 1], "offset": [5, -7, 0]}]), "rod")
    with pytest.raises(PopcodeError, match="does not map the mesh onto itself"):
        check_symmetries(bar, _info(bar, symmetries_discrete=_about_z(2)), "bar")


def test_wrong_four_fold_names_the_transform_and_its_distance() -> None:
    with pytest.raises(PopcodeError) as error:
        check_symmetries(_bar(), _info(_bar(), symmetries_discrete=_about_z(4)), "object 3 (flange.ply)")
    message = str(error.value)
    assert "object 3 (flange.ply): symmetries_discrete[0] (rotation 90.0 deg about (0, 0, 1))" in message
    assert "does not map the mesh onto itself" in message
    share = float(message.split("samples land ")[1].split(" %")[0])
    assert share > 10  # a quarter turn moves the bar's ends far off its surface


def test_generator_alone_is_refused_with_the_missing_composition() -> None:
    mesh = _dodecagon()
    with pytest.raises(PopcodeError) as error:
        check_symmetries(mesh, _info(mesh, symmetries_discrete=[_flat((0, 0, 1), 30)]), "nut")
    message = str(error.value)
    assert "not closed under composition" in message
    assert "symmetries_discrete[0] after symmetries_discrete[0] (rotation 60.0 deg about (0, 0, 1))" in message
    assert "declare all 11 non-identity symmetries" in message


def test_wrong_continuous_axis_is_refused() -> None:
    mesh = _rod()
    with pytest.raises(PopcodeError, match=r"symmetries_continuous\[0\] \(axis \(1, 0, 0\) through .* turned"):
        check_symmetries(mesh, _info(mesh, symmetries_continuous=[{"axis": [1, 0, 0], "offset": [0, 0, 0]}]),
                         "rod")


def test_no_declared_symmetry_needs_no_surface_area() -> None:
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0]], faces=[[0, 1, 2]], process=False)
    check_symmetries(flat, {"diameter": 2.0}, "flat")
    with pytest.raises(PopcodeError, match="flat: the mesh has no surface area"):
        check_symmetries(flat, {"diameter": 2.0, "symmetries_discrete": _about_z(2)}, "flat")


@pytest.mark.parametrize("part", BUILTIN_PARTS, ids=lambda part: part.name)
def test_builtin_parts_pass_their_declared_symmetries(part) -> None:
    """Every declaration is checked (a wrong one raises); how long the check takes is not a test's to judge."""
    mesh = build_part(part.obj_id)
    check_symmetries(mesh, model_info(mesh, part.symmetries), part.name)


def _models(folder: Path, mesh: trimesh.Trimesh, **symmetries: list) -> Path:
    folder.mkdir()
    mesh.export(folder / "obj_000003.ply")
    (folder / "models_info.json").write_text(json.dumps({"3": _info(mesh, **symmetries)}))
    return folder


def test_checked_once_per_file_and_declaration(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    models = _models(tmp_path / "models", _bar(), symmetries_discrete=_about_z(2))
    info = json.loads((models / "models_info.json").read_text())["3"]
    check_object_symmetries(models / "obj_000003.ply", info, 3)

    def no_second_look(*args: object) -> None:
        raise AssertionError("sampled again")

    monkeypatch.setattr(symmetry_check, "surface_sample", no_second_look)
    check_object_symmetries(models / "obj_000003.ply", info, 3)
    with pytest.raises(AssertionError):  # another declaration is checked anew
        check_object_symmetries(models / "obj_000003.ply", {**info, "symmetries_discrete": _about_z(4)}, 3)


def test_export_checks_the_meshes_it_reads(tmp_path: Path) -> None:
    models = _models(tmp_path / "models", _bar(), symmetries_discrete=_about_z(4))
    info = json.loads((models / "models_info.json").read_text())
    with pytest.raises(PopcodeError, match=r"object 3 \(.*obj_000003.ply\): symmetries_discrete\[0\]"):
        with_hull_points({3: info["3"]}, models)


def test_missing_mesh_is_a_warning(tmp_path: Path) -> None:
    with pytest.warns(UserWarning, match=r"objects \[3\]: their declared symmetries are not checked"):
        check_models_symmetries(tmp_path, {3: {"diameter": 1.0, "symmetries_discrete": _about_z(2)}}, [3])
