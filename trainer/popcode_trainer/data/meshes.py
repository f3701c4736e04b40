"""Object meshes as the BOP toolkit reads them: PLY/OBJ in mm, ASCII PLY vertices with every digit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError


def _ascii_ply_vertices(path: Path) -> np.ndarray | None:
    """The x, y, z of an ASCII PLY's vertices read as float64, as the BOP toolkit reads them; None for other files.

    trimesh parses ``property float`` as float32, which moves ADI and MSSD by ~1e-9 relative.
    """
    if path.suffix.lower() != ".ply":
        return None
    with path.open("rb") as handle:
        if handle.readline().strip() != b"ply" or not handle.readline().startswith(b"format ascii"):
            return None
        header = []
        for line in handle:
            header.append(line.decode("ascii", "replace").split())
            if header[-1][:1] == ["end_header"]:
                break
        element, count, properties, skip = None, 0, [], 0
        for words in header:
            if words[:1] == ["element"]:
                if element == "vertex":
                    break
                element, count = words[1], int(words[2])
                if element != "vertex":
                    skip += count  # elements before the vertices (rare) are whole lines too
            elif words[:1] == ["property"] and element == "vertex":
                properties.append(words[-1])
        for _ in range(skip):
            handle.readline()
        rows = [handle.readline().split() for _ in range(count)]
    columns = [properties.index(axis) for axis in ("x", "y", "z")]
    return np.array([[float(row[c]) for c in columns] for row in rows], dtype=np.float64)


def _check_geometry(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Refuse what trimesh loads without a word but OpenGL, sampling and the metrics cannot use."""
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise PopcodeError(f"model {path}: a triangle names vertex {int(faces.max())}, but the file has "
                           f"{len(vertices)} vertices")
    if not np.isfinite(vertices).all():
        raise PopcodeError(f"model {path}: vertex coordinates contain NaN or inf")
    corners = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    if not area > 0.0:
        raise PopcodeError(f"model {path} is degenerate: its {len(faces)} triangles have no area")


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """A PLY/OBJ model (mm) as one triangle mesh; a clear error if it does not load.

    ASCII PLY vertices keep every digit of the file (float64), as in the BOP toolkit.
    """
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"model file not found: {path}")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for broken files
        raise PopcodeError(f"cannot load model {path}: {error}") from error
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise PopcodeError(f"model {path} has no triangles")
    _check_geometry(path, np.asarray(loaded.vertices), np.asarray(loaded.faces))
    try:
        exact = _ascii_ply_vertices(path)
    except (ValueError, IndexError, UnicodeDecodeError) as error:
        raise PopcodeError(f"cannot read the vertices of {path}: {error}") from error
    if exact is not None:
        if exact.shape != loaded.vertices.shape or not np.allclose(exact, loaded.vertices, rtol=1e-6, atol=1e-6):
            raise PopcodeError(f"the vertices of {path} read two ways disagree: not a well-formed ASCII PLY")
        loaded.vertices = exact
    return loaded
