"""A picture of each estimate: its box, the object's axes, the projected hull outline, object id and confidence.

OpenCV only; the picture is BGR uint8 as OpenCV writes it. Model x is drawn red, y green, z blue.

**Symmetric objects.** Poses ``R`` and ``R·S`` (``S`` a symmetry rotation) are the same estimate, so the picture
must not tell them apart. Rule: a model direction ``v`` is drawn as the set of segments from the centre to
``R·S_k·v`` over every symmetry rotation ``S_k`` (its *orbit*). The symmetries form a group, so for an equivalent
pose ``R·S_j`` the products ``S_j·S_k`` run over the same set and the picture is identical. What that gives:

- an axis every symmetry fixes (z of a part 2-fold about z) is an arrow;
- an axis the symmetries only reverse (x and y of that part) is an undirected line through the centre;
- axes the symmetries exchange (x and y of a 4-fold part) are one set of lines in the mix of their colours
  (an orbit's colour mixes red, green and blue by how much of model x, y and z its directions hold);
- a continuous symmetry about ``a``: only the orbit of ``a`` is drawn (an arrow, or a line when a discrete
  symmetry reverses it) with an ellipse around it for the free rotation; the other axes are undefined.

The axes start at the point every symmetry maps onto itself (the model origin when the symmetries have no
translation); the hull outline is the convex hull of every symmetric image of the hull points (revolved
about the axis of a continuous symmetry), so it too is the same for every equivalent pose.

**Placement.** With a translation ``t_m2c_mm`` the points are projected with the camera
(:mod:`popcode_runtime.geometry.camera`) and the axes are as long as half the box's longer side at the object's
depth. Without one (or one that puts the object behind the camera) the axes start at the box centre and are drawn
orthographically, the camera-frame x and y of each direction, half the box's longer side long: a picture of the
rotation, not of a position. The ellipse of a continuous symmetry is drawn orthographically in both cases (weak
perspective at the object's depth).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..base.checks import number_array
from ..base.errors import PopcodeError
from ..geometry.camera import parse_camera_matrix, project_camera_points
from ..geometry.crop import box_centre, check_image
from ..geometry.symmetries import (
    SymmetryClass,
    continuous_axis,
    continuous_symmetries,
    discrete_transforms,
    symmetry_class,
    symmetry_rotations,
)
from ..geometry.translation import object_points_mm
from ..inference.prediction import Prediction
from ..model.metadata import ModelMetadata

AXIS_COLOURS_BGR = np.array([[0, 0, 255], [0, 255, 0], [255, 0, 0]], dtype=np.float64)  # model x, y, z
BOX_COLOUR_BGR = (255, 255, 255)
HULL_COLOUR_BGR = (255, 0, 255)
TEXT_COLOUR_BGR = (255, 255, 255)
TEXT_BACKGROUND_BGR = (0, 0, 0)
AXIS_LENGTH_OF_BOX = 0.5  # axis length / the box's longer side
NEAREST_AXIS_END = 0.5  # axis length at most this fraction of the centre's depth: every end stays in front
ELLIPSE_OF_AXIS = 0.5  # radius of a continuous symmetry's ellipse / axis length
ARROW_TIP = 0.2  # arrow head / arrow length
REVOLVE_STEPS = 72  # copies of the hull points about a continuous symmetry axis
DIRECTION_DECIMALS = 6  # orbit directions equal to this many decimals are one
MAX_DRAW_PX = 1e5  # OpenCV draws with 32-bit integer pixels; a degenerate pose projects further


@dataclass(frozen=True)
class AxisGlyph:
    """The orbit of one model direction under the object's symmetries, drawn as segments from the centre."""

    directions_m: np.ndarray  # (k, 3) unit directions, model frame
    colour_bgr: tuple[int, int, int]
    arrow: bool  # a head on the tip: only when every symmetry fixes the direction (k == 1)


def axis_glyphs(info: Mapping[str, Any]) -> list[AxisGlyph]:
    """What of the object's axes every equivalent pose shares: x, y, z (or the continuous symmetry axis) as orbits.

    Orbits that are the same set (the x and y of a 4-fold part) are drawn once.
    """
    rotations = symmetry_rotations(info)
    bases = [continuous_axis(info)] if symmetry_class(info) == SymmetryClass.CONTINUOUS else list(np.eye(3))
    glyphs: list[AxisGlyph] = []
    for base in bases:
        orbit = np.unique(np.round(rotations @ base, DIRECTION_DECIMALS) + 0.0, axis=0)  # + 0.0: no -0.0
        if any(np.array_equal(orbit, glyph.directions_m) for glyph in glyphs):
            continue
        weights = np.abs(orbit).sum(axis=0)
        colour = (weights / weights.max()) @ AXIS_COLOURS_BGR
        glyphs.append(AxisGlyph(orbit, tuple(int(round(c)) for c in colour), arrow=len(orbit) == 1))
    return glyphs


def symmetry_centre_mm(info: Mapping[str, Any]) -> np.ndarray:
    """The model point ``(3,)`` [mm] every symmetry maps onto itself, the one nearest the origin.

    The origin for an object without symmetries or whose symmetries have no translation.
    """
    discrete = discrete_transforms(info)
    matrices = [R - np.eye(3) for R in discrete.R]
    targets = [-t for t in discrete.t_mm]
    for axis, offset in continuous_symmetries(info):
        across = np.eye(3) - np.outer(axis, axis)  # the point lies on the axis through ``offset``
        matrices.append(across)
        targets.append(across @ offset)
    return np.linalg.lstsq(np.concatenate(matrices), np.concatenate(targets), rcond=None)[0]


def estimate_label(prediction: Prediction) -> list[str]:
    """The text lines beside an estimate: object id and calibrated confidence, or the raw score and that it is not
    a confidence (models without a calibrator)."""
    obj = "obj ?" if prediction.obj_id is None else f"obj {prediction.obj_id}"
    if prediction.confidence is None:
        return [f"{obj} score {prediction.score:.2f}", "no calibrated confidence"]
    return [f"{obj} confidence {prediction.confidence:.2f}"]


def draw_predictions(image: np.ndarray, predictions: Sequence[Prediction], metadata: ModelMetadata,
                     K: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """A BGR uint8 copy of ``image`` with every estimate drawn (see the module's docstring for what and how).

    ``image`` is what :meth:`PoseEstimator.predict` takes (grey or RGB; uint8, uint16 or float in [0, 1]);
    ``metadata`` the model's, for the objects' symmetries and hull points; ``K`` (``fx, fy, cx, cy`` or 3x3)
    is needed when a prediction has a translation.
    """
    picture = _bgr_uint8(image)
    for prediction in predictions:
        _check_prediction(prediction, metadata)
    camera = None if K is None else parse_camera_matrix(K)
    if camera is None and any(p.t_m2c_mm is not None for p in predictions):
        raise PopcodeError("drawing an estimate with a translation needs the camera matrix K")
    style = _Style.for_shape(picture.shape)
    for prediction in predictions:
        _draw_geometry(picture, prediction, metadata.objects.get(prediction.obj_id, {}), camera, style)
    for prediction in predictions:  # last, so that no other estimate's lines cover a label
        _draw_label(picture, prediction, style)
    return picture


def draw_models(image: np.ndarray, drawn: Sequence[tuple[ModelMetadata, Sequence[Prediction]]],
                K: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """A BGR uint8 copy of ``image`` with the estimates of several models, each drawn with its model's metadata
    (a frame whose parts several models estimate: ``popcode run``, ``popcode predict --detector``)."""
    picture = _bgr_uint8(image)
    for metadata, predictions in drawn:
        picture = draw_predictions(picture[..., ::-1], predictions, metadata, K)  # it takes RGB, gives BGR
    return picture


def _check_prediction(prediction: Prediction, metadata: ModelMetadata) -> None:
    """Finite numbers of the right shapes and an object the model knows (or none: a model not told which)."""
    if not isinstance(prediction, Prediction):
        raise PopcodeError(f"draw_predictions draws Prediction objects, got {type(prediction).__name__}")
    number_array(prediction.R_m2c, "a prediction's R_m2c", (3, 3))
    number_array(prediction.box, "a prediction's box", (4,))
    if prediction.t_m2c_mm is not None:
        number_array(prediction.t_m2c_mm, "a prediction's t_m2c_mm", (3,))
    if prediction.obj_id is not None and prediction.obj_id not in metadata.objects:
        raise PopcodeError(f"object {prediction.obj_id} is not in this model (it knows {sorted(metadata.objects)})")


@dataclass(frozen=True)
class _Style:
    thickness: int
    font_scale: float

    @classmethod
    def for_shape(cls, shape: tuple[int, ...]) -> _Style:
        side = min(shape[:2])
        return cls(thickness=max(1, round(side / 300)), font_scale=float(np.clip(side / 900, 0.3, 1.2)))


def _bgr_uint8(image: np.ndarray) -> np.ndarray:
    image = check_image(image)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        image = (image * 255.0 + 0.5).astype(np.uint8)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(image[..., ::-1])  # the runtime's colour images are RGB


def _pixel(point_px: np.ndarray) -> tuple[int, int]:
    x, y = np.clip(np.round(point_px), -MAX_DRAW_PX, MAX_DRAW_PX).astype(int)
    return int(x), int(y)


@dataclass(frozen=True)
class _Placement:
    """Where the axes start and how a camera-frame unit direction becomes the pixel of an axis end."""

    centre_px: np.ndarray  # (2,)
    axis_length_px: float  # at the centre (weak perspective with a translation)
    axis_end_px: Callable[[np.ndarray], np.ndarray]  # (N, 3) camera-frame unit directions -> (N, 2) pixels
    centre_c_mm: np.ndarray | None  # (3,) with a translation


def _placement(prediction: Prediction, camera: np.ndarray | None, centre_m_mm: np.ndarray) -> _Placement:
    box_side_px = max(prediction.box[2], prediction.box[3])
    if prediction.t_m2c_mm is not None and camera is not None:
        centre_c_mm = prediction.R_m2c @ centre_m_mm + prediction.t_m2c_mm
        if centre_c_mm[2] > 0:
            focal_px = (camera[0, 0] + camera[1, 1]) / 2.0
            length_mm = min(AXIS_LENGTH_OF_BOX * box_side_px * centre_c_mm[2] / focal_px,
                            NEAREST_AXIS_END * centre_c_mm[2])
            return _Placement(project_camera_points(centre_c_mm, camera), focal_px * length_mm / centre_c_mm[2],
                              lambda d: project_camera_points(centre_c_mm + length_mm * d, camera), centre_c_mm)
    centre_px = box_centre(prediction.box)
    length_px = AXIS_LENGTH_OF_BOX * box_side_px
    return _Placement(centre_px, length_px, lambda d: centre_px + length_px * d[:, :2], None)


def _draw_geometry(picture: np.ndarray, prediction: Prediction, info: Mapping[str, Any], camera: np.ndarray | None,
                   style: _Style) -> None:
    x, y, w, h = prediction.box
    cv2.rectangle(picture, _pixel(np.array([x, y])), _pixel(np.array([x + w, y + h])), BOX_COLOUR_BGR,
                  style.thickness, cv2.LINE_8)
    centre_m_mm = symmetry_centre_mm(info)
    placement = _placement(prediction, camera, centre_m_mm)
    if placement.centre_c_mm is not None:
        _draw_hull(picture, prediction, info, camera, centre_m_mm, style)
    centre = _pixel(placement.centre_px)
    glyphs = axis_glyphs(info)
    for glyph in glyphs:
        for end_px in placement.axis_end_px(glyph.directions_m @ prediction.R_m2c.T):
            if glyph.arrow:
                cv2.arrowedLine(picture, centre, _pixel(end_px), glyph.colour_bgr, style.thickness, cv2.LINE_8,
                                tipLength=ARROW_TIP)
            else:
                cv2.line(picture, centre, _pixel(end_px), glyph.colour_bgr, style.thickness, cv2.LINE_8)
    if symmetry_class(info) == SymmetryClass.CONTINUOUS:
        _draw_free_rotation(picture, prediction.R_m2c @ continuous_axis(info), placement, glyphs[0].colour_bgr,
                            style)


def _draw_free_rotation(picture: np.ndarray, axis_c: np.ndarray, placement: _Placement,
                        colour_bgr: tuple[int, int, int], style: _Style) -> None:
    """An ellipse about a continuous symmetry axis: a circle around it, seen orthographically."""
    radius_px = ELLIPSE_OF_AXIS * placement.axis_length_px
    across_deg = float(np.degrees(np.arctan2(axis_c[1], axis_c[0]))) + 90.0  # the circle's widest extent
    half_axes = (int(round(min(radius_px, MAX_DRAW_PX))), int(round(min(radius_px * abs(axis_c[2]), MAX_DRAW_PX))))
    cv2.ellipse(picture, _pixel(placement.centre_px), half_axes, across_deg, 0.0, 360.0, colour_bgr,
                style.thickness, cv2.LINE_8)


def _draw_hull(picture: np.ndarray, prediction: Prediction, info: Mapping[str, Any], camera: np.ndarray,
               centre_m_mm: np.ndarray, style: _Style) -> None:
    """The outline of the object's projected hull points and all their symmetric images (none without points)."""
    try:
        points_m_mm = object_points_mm(info)
    except PopcodeError:  # neither hull points nor extents: nothing to outline
        return
    discrete = discrete_transforms(info)
    points_m_mm = (points_m_mm @ discrete.R.transpose(0, 2, 1) + discrete.t_mm[:, None]).reshape(-1, 3)
    if symmetry_class(info) == SymmetryClass.CONTINUOUS:
        points_c_mm = _revolved_camera_points(points_m_mm, centre_m_mm, continuous_axis(info), prediction)
    else:
        points_c_mm = points_m_mm @ prediction.R_m2c.T + prediction.t_m2c_mm
    if points_c_mm[:, 2].min() <= 0:  # part of the object behind the camera: no outline to speak of
        return
    pixels = np.clip(project_camera_points(points_c_mm, camera), -MAX_DRAW_PX, MAX_DRAW_PX)
    hull = cv2.convexHull(np.round(pixels).astype(np.int32))
    cv2.polylines(picture, [hull], True, HULL_COLOUR_BGR, style.thickness, cv2.LINE_8)


def _revolved_camera_points(points_m_mm: np.ndarray, centre_m_mm: np.ndarray, axis_m: np.ndarray,
                            prediction: Prediction) -> np.ndarray:
    """Camera-frame points ``(P * REVOLVE_STEPS, 3)`` [mm] of the hull points swept about the symmetry axis.

    Built from the camera-frame axis alone, so every rotation about it gives the same points.
    """
    relative = points_m_mm - centre_m_mm
    height = relative @ axis_m
    radius = np.linalg.norm(relative - height[:, None] * axis_m, axis=1)
    axis_c = prediction.R_m2c @ axis_m
    across = np.eye(3)[np.argmin(np.abs(axis_c))]
    u = np.cross(axis_c, across)
    u /= np.linalg.norm(u)
    v = np.cross(axis_c, u)
    angles = np.linspace(0.0, 2.0 * np.pi, REVOLVE_STEPS, endpoint=False)
    ring = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v  # (S, 3)
    centre_c_mm = prediction.R_m2c @ centre_m_mm + prediction.t_m2c_mm
    points = centre_c_mm + height[:, None, None] * axis_c + radius[:, None, None] * ring[None]
    return points.reshape(-1, 3)


def _draw_label(picture: np.ndarray, prediction: Prediction, style: _Style) -> None:
    """The label's lines on a dark band above the box's top-left corner, else below the box, else inside it."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    lines = estimate_label(prediction)
    sizes = [cv2.getTextSize(line, font, style.font_scale, 1) for line in lines]
    text_height = max(size[1] for size, _ in sizes)
    line_height = text_height + max(baseline for _, baseline in sizes) + 2
    width = max(size[0] for size, _ in sizes) + 2
    band_height = len(lines) * line_height
    height_px, width_px = picture.shape[:2]
    left, box_top = _pixel(np.array(prediction.box[:2]))
    box_bottom = _pixel(np.array(prediction.box[:2]) + prediction.box[2:])[1]
    if box_top - band_height >= 0:  # the band's rows are top .. top + band_height - 1
        top = box_top - band_height
    elif box_bottom + 1 + band_height <= height_px:
        top = box_bottom + 1
    else:
        top = box_top
    left = int(np.clip(left, 0, max(width_px - width, 0)))
    top = int(np.clip(top, 0, max(height_px - band_height, 0)))
    cv2.rectangle(picture, (left, top), (left + width - 1, top + band_height - 1), TEXT_BACKGROUND_BGR, -1)
    for index, line in enumerate(lines):
        baseline_y = top + index * line_height + 1 + text_height
        cv2.putText(picture, line, (left + 1, baseline_y), font, style.font_scale, TEXT_COLOUR_BGR, 1, cv2.LINE_AA)
