"""A scene's BOP annotations as the BOP toolkit's ``calc_gt_masks`` and ``calc_gt_info`` compute them.

``mask`` is the part rendered alone, ``mask_visib`` the pixels of that mask
where the part is not more than ``visib_delta_mm`` behind the scene's depth,
``px_count_all`` counts the whole silhouette including what the image border
cuts off, and the boxes of an instance with no visible pixel are
``[-1, -1, -1, -1]``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..metrics.visibility import depth_to_distance, visible_mask_gt
from .gl import PixelRegion
from .render import mask_box

BOP_VISIB_DELTA_MM = 15.0  # the BOP toolkit's calc_gt_info / calc_gt_masks tolerance


def instance_gt_info(depth_alone_mm: np.ndarray, depth_scene_mm: np.ndarray, K: np.ndarray, delta_mm: float,
                     px_count_all: int | None = None, bbox_obj: list[int] | None = None,
                     region: PixelRegion | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """``mask``, ``mask_visib`` ``(H, W)`` bool and the ``scene_gt_info`` entry of one instance.

    ``depth_alone_mm``: the instance rendered alone; ``depth_scene_mm``: the whole scene (0 where
    nothing is). ``px_count_all`` and ``bbox_obj`` of the whole silhouette, when the border cuts it,
    come from a larger rendering; by default they are the in-image mask's. With ``region``
    ``(x0, y0, x1, y1)``, ``depth_alone_mm`` is only that part of the image, nothing outside it.
    """
    height, width = depth_scene_mm.shape
    x0, y0, x1, y1 = (0, 0, width, height) if region is None else region
    K_region = np.array(K, dtype=np.float64)
    K_region[:2, 2] -= [x0, y0]  # same distances as over the whole image: camera_matrix's cx, cy are multiples of 0.5
    scene_mm = depth_scene_mm[y0:y1, x0:x1]
    mask_in = depth_alone_mm > 0
    visib_in = visible_mask_gt(depth_to_distance(scene_mm, K_region), depth_to_distance(depth_alone_mm, K_region),
                               delta_mm)
    mask, mask_visib = np.zeros((height, width), bool), np.zeros((height, width), bool)
    mask[y0:y1, x0:x1], mask_visib[y0:y1, x0:x1] = mask_in, visib_in
    px_count_all = int(mask_in.sum()) if px_count_all is None else int(px_count_all)
    px_count_visib = int(visib_in.sum())
    info = {
        "bbox_obj": (moved_box(mask_in, x0, y0) if bbox_obj is None else list(bbox_obj)) if px_count_visib
        else [-1] * 4,
        "bbox_visib": moved_box(visib_in, x0, y0),
        "px_count_all": px_count_all,
        "px_count_valid": int((scene_mm[mask_in] > 0).sum()),
        "px_count_visib": px_count_visib,
        "visib_fract": px_count_visib / px_count_all if px_count_all else 0.0,
    }
    return mask, mask_visib, info


def moved_box(mask: np.ndarray, dx: int, dy: int) -> list[int]:
    """:func:`.render.mask_box` of ``mask`` with its first pixel moved by ``(dx, dy)``; no box stays ``[-1] * 4``."""
    x, y, w, h = mask_box(mask)
    return [x + dx, y + dy, w, h] if w >= 0 else [-1] * 4
