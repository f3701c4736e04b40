"""Object meshes as the BOP toolkit reads them: PLY/OBJ in mm, ASCII PLY vertices with every digit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError

# A mesh's vertices and its faces may each number this many: loading and checking one at the limit takes about
# 1.2 GB and 5 s (a finer scan is decimated first; the renders and metrics gain nothing from more).
MAX_MESH_ELEMENTS = 4_000_000
MAX_MESH_BYTES = 1 << 29  # 512 MiB: an ASCII PLY at the element limit, with normals and colours, fits
MAX_PLY_HEADER_LINES = 1000
_LINE_BYTES = 1 << 12  # a header line read at a time: a binary file without a newline is not read whole
_PLY_SIZES = {name: size for size, names in ((1, "char uchar int8 uint8"), (2, "short ushort int16 uint16"),
                                             (4, "int uint int32 uint32 float float32"), (8, "double float64"))
              for name in names.split()}


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


def _check_ply_header(path: Path, size: int) -> None:
    """Refuse a PLY whose header claims more elements than :data:`MAX_MESH_ELEMENTS`, or more than the file's bytes
    hold, before any reader sizes arrays or loops by those counts (a header can claim billions)."""
    with path.open("rb") as handle:
        if handle.readline(_LINE_BYTES).strip() != b"ply":
            return  # not a PLY: the loader names it
        binary = b"binary" in handle.readline(_LINE_BYTES)
        least, count, counts = 0, 0, []
        for _ in range(MAX_PLY_HEADER_LINES):
            words = handle.readline(_LINE_BYTES).decode("ascii", "replace").split()
            if words[:1] == ["end_header"]:
                break
            if words[:1] == ["element"]:  # a malformed element line counts nothing here: the loader names it
                name, count = "".join(words[1:2]), int(words[2]) if len(words) == 3 and words[2].isdigit() else 0
                counts.append(f"{count:,} {name}")
                if count > MAX_MESH_ELEMENTS:
                    raise PopcodeError(f"model {path}: its header claims {count:,} {name} elements; at most "
                                       f"{MAX_MESH_ELEMENTS:,} are allowed: decimate the mesh")
            elif words[:1] == ["property"] and len(words) >= 3:
                # the fewest bytes a property of each element takes: ASCII "0 "; binary its size (a list: its count's)
                least += count * (_PLY_SIZES.get(words[2 if words[1] == "list" else 1], 1) if binary else 2)
        else:
            raise PopcodeError(f"cannot load model {path}: no end_header within {MAX_PLY_HEADER_LINES} lines; "
                               "not a PLY")
        data = size - handle.tell()
    if least > data + 1:  # + 1: an ASCII file's last line may end without its newline
        raise PopcodeError(f"model {path}: its header claims {', '.join(counts)} elements, more than its {data:,} "
                           "bytes of data hold: the file is truncated or corrupt")


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """A PLY/OBJ model (mm) as one triangle mesh; a clear error if it does not load.

    ASCII PLY vertices keep every digit of the file (float64), as in the BOP toolkit.
    """
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"model file not found: {path}")
    size = path.stat().st_size
    if size > MAX_MESH_BYTES:
        raise PopcodeError(f"model {path} holds {size:,} bytes; at most {MAX_MESH_BYTES:,} are allowed: decimate "
                           "the mesh")
    _check_ply_header(path, size)
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for broken files
        raise PopcodeError(f"cannot load model {path}: {error}") from error
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise PopcodeError(f"model {path} has no triangles")
    if max(len(loaded.vertices), len(loaded.faces)) > MAX_MESH_ELEMENTS:  # formats without a header that says
        raise PopcodeError(f"model {path} has {len(loaded.vertices):,} vertices and {len(loaded.faces):,} faces; at "
                           f"most {MAX_MESH_ELEMENTS:,} of each are allowed: decimate the mesh")
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
