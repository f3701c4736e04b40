"""BOP19 results files: ``scene_id,im_id,obj_id,score,R,t,time`` as the official toolkit reads them.

``R`` is the model-to-camera rotation as 9 space-separated numbers in row-major
order, ``t`` the translation as 3 numbers in mm, ``time`` the run time in seconds
of the image's estimates (-1 when unknown). Numbers are written with ``repr``, the
shortest text that reads back to the same float, so files round-trip exactly.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.errors import PopcodeError
from ..base.files import name_id, write_bytes_atomic

HEADER = "scene_id,im_id,obj_id,score,R,t,time"


@dataclass(frozen=True)
class PoseEstimate:
    """One pose estimate of a BOP19 results file."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R_m2c: np.ndarray  # (3, 3)
    t_m2c_mm: np.ndarray  # (3,)
    time_s: float = -1.0


def _numbers(values: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(values, dtype=np.float64).reshape(-1))


def format_estimate(est: PoseEstimate) -> str:
    """One line of a results file (no newline)."""
    if np.shape(est.R_m2c) != (3, 3) or np.size(est.t_m2c_mm) != 3:
        raise PopcodeError(
            f"estimate for scene {est.scene_id} image {est.im_id} object {est.obj_id}: "
            f"R must be 3x3 and t 3 numbers, got {np.shape(est.R_m2c)} and {np.shape(est.t_m2c_mm)}"
        )
    return (f"{est.scene_id},{est.im_id},{est.obj_id},{float(est.score)!r},"
            f"{_numbers(est.R_m2c)},{_numbers(est.t_m2c_mm)},{float(est.time_s)!r}")


def write_bop19_results(path: str | Path, estimates: Iterable[PoseEstimate]) -> None:
    """Write estimates to a BOP19 results CSV (header line, then one line per estimate), atomically."""
    write_bop19_lines(path, [format_estimate(est) for est in estimates])


def write_bop19_lines(path: str | Path, lines: Iterable[str]) -> None:
    """The header and formatted estimate lines as a results file, written atomically."""
    write_bytes_atomic(Path(path), ("\n".join([HEADER, *lines]) + "\n").encode())


def parse_estimate(line: str, where: str) -> PoseEstimate:
    """One line of a results file; a malformed one raises with ``where`` (file and line) named."""
    fields = line.split(",")
    if len(fields) != 7:
        raise PopcodeError(f"{where}: expected 7 comma-separated fields ({HEADER}), found {len(fields)}")
    try:
        R = np.array(fields[4].split(), dtype=np.float64)
        t = np.array(fields[5].split(), dtype=np.float64)
        if R.size != 9 or t.size != 3:
            raise ValueError(f"R has {R.size} numbers (needs 9) and t {t.size} (needs 3)")
        ids = [name_id(field) for field in fields[:3]]
        if None in ids:
            raise ValueError(f"scene_id, im_id and obj_id must be whole numbers >= 0, got {fields[:3]}")
        score, time_s = float(fields[3]), float(fields[6])
        if not (np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite([score, time_s]).all()):
            raise ValueError("score, R, t and time must be finite numbers (NaN or inf found)")
        return PoseEstimate(scene_id=ids[0], im_id=ids[1], obj_id=ids[2], score=score,  # type: ignore[arg-type]
                            R_m2c=R.reshape(3, 3), t_m2c_mm=t, time_s=time_s)
    except ValueError as error:
        raise PopcodeError(f"{where}: {error}") from error


def read_bop19_results(path: str | Path) -> list[PoseEstimate]:
    """Read a BOP19 results CSV; a malformed line raises with its line number."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"results file not found: {path}" if not path.exists() else f"{path} is not a file")
    try:
        lines = path.read_bytes().decode("utf-8").splitlines()
    except UnicodeDecodeError as error:
        raise PopcodeError(f"{path} is not a UTF-8 text file ({error.reason} at byte {error.start})") from error
    if not lines or lines[0].strip() != HEADER:
        raise PopcodeError(f"{path}: the first line must be the header {HEADER!r}")
    return [
        parse_estimate(line.strip(), f"{path}:{number}")
        for number, line in enumerate(lines[1:], start=2)
        if line.strip()
    ]
