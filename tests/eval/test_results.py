"""BOP19 results CSV: exact round trip and clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.bop19_csv import HEADER, PoseEstimate, read_bop19_results, write_bop19_results
from popcode_runtime.geometry.rotations import random_rotations


def test_results_round_trip_exactly(tmp_path):
    rng = np.random.default_rng(3)
    estimates = [
        PoseEstimate(scene_id=1, im_id=i, obj_id=5 + i, score=float(rng.random()), R_m2c=R,
                     t_m2c_mm=rng.normal(size=3) * 100 + [0, 0, 700], time_s=0.0032)
        for i, R in enumerate(random_rotations(3, rng))
    ]
    path = tmp_path / "pc_tless-test.csv"
    write_bop19_results(path, estimates)
    lines = path.read_text().splitlines()
    assert lines[0] == HEADER and len(lines) == 4
    fields = lines[1].split(",")
    assert len(fields) == 7 and len(fields[4].split()) == 9 and len(fields[5].split()) == 3
    assert float(fields[4].split()[1]) == estimates[0].R_m2c[0, 1]  # row-major
    back = read_bop19_results(path)
    assert len(back) == 3
    for a, b in zip(estimates, back, strict=True):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time_s) == (b.scene_id, b.im_id, b.obj_id, b.score, b.time_s)
        np.testing.assert_array_equal(a.R_m2c, b.R_m2c)
        np.testing.assert_array_equal(a.t_m2c_mm, b.t_m2c_mm)


def test_unknown_time_is_minus_one(tmp_path):
    path = tmp_path / "r.csv"
    write_bop19_results(path, [PoseEstimate(1, 2, 3, 1.0, np.eye(3), np.zeros(3))])
    assert path.read_text().splitlines()[1].endswith(",-1.0")
    assert read_bop19_results(path)[0].time_s == -1.0


def test_bad_files_name_the_line(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text(HEADER + "\n1,2,3,1.0,1 0 0 0 1 0 0 0,0 0 700,-1\n")
    with pytest.raises(PopcodeError, match="bad.csv:2: R has 8 numbers"):
        read_bop19_results(path)
    path.write_text("scene,im\n")
    with pytest.raises(PopcodeError, match="header"):
        read_bop19_results(path)
    with pytest.raises(PopcodeError, match="R must be 3x3"):
        write_bop19_results(path, [PoseEstimate(1, 2, 3, 1.0, np.eye(4), np.zeros(3))])


@pytest.mark.parametrize(("line", "message"), [
    ("1,2,3,nan,1 0 0 0 1 0 0 0 1,0 0 700,-1", "must be finite numbers"),  # evaluate scored it as "no estimate"
    ("1,2,3,1.0,1 0 0 0 1 0 0 0 1,0 inf 700,-1", "must be finite numbers"),
    ("1,2,3,1.0,1 0 0 0 1 0 0 0 1,0 0 700,nan", "must be finite numbers"),
    ("1,2,3.5,1.0,1 0 0 0 1 0 0 0 1,0 0 700,-1", "must be whole numbers >= 0"),
    ("1,-2,3,1.0,1 0 0 0 1 0 0 0 1,0 0 700,-1", "must be whole numbers >= 0"),
    ("\u0661,2,3,1.0,1 0 0 0 1 0 0 0 1,0 0 700,-1", "must be whole numbers >= 0"),  # an Arabic-Indic one
])
def test_values_outside_the_format_name_the_line(tmp_path, line: str, message: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(f"{HEADER}\n{line}\n")
    with pytest.raises(PopcodeError, match=f"bad.csv:2: .*{message}"):
        read_bop19_results(path)
