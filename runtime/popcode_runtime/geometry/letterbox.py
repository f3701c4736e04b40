"""Where a camera frame lies in a detector's fixed input: scaled to fit whole, centred, the rest padded.

A frame of the input's aspect fills it; one of another aspect (16:9, portrait)
is scaled by the same factor on both axes until its longer side (relative to the
input) fits and the other side is padded, so a part keeps its shape. The scaled
size is rounded to whole pixels, so each axis has its own exact scale
``scaled / frame``; the pad is split evenly, in whole pixels. Boxes are edges
``(x0, y0, x1, y1)`` in pixels, the convention of OpenCV's resize: an edge at
``u`` in the frame lies at ``u * scale + offset`` in the input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Letterbox:
    """A frame of ``frame`` (columns, rows) in an input of ``size``: resized to ``scaled``, placed at ``offset``."""

    frame: tuple[int, int]
    size: tuple[int, int]
    scaled: tuple[int, int]
    offset: tuple[int, int]

    @classmethod
    def fit(cls, frame: tuple[int, int], size: tuple[int, int]) -> Letterbox:
        """The largest uniform scaling of ``frame`` (columns, rows) that fits in ``size`` (width, height)."""
        scale = min(size[0] / frame[0], size[1] / frame[1])
        scaled = tuple(min(limit, max(1, round(side * scale))) for side, limit in zip(frame, size, strict=True))
        offset = tuple((limit - side) // 2 for side, limit in zip(scaled, size, strict=True))
        return cls(tuple(frame), tuple(size), scaled, offset)

    def _scale(self) -> np.ndarray:
        return np.array([self.scaled[0] / self.frame[0], self.scaled[1] / self.frame[1]] * 2)

    def to_input(self, edges: np.ndarray) -> np.ndarray:
        """Boxes ``(N, 4)`` x0, y0, x1, y1 in the frame's pixels -> in the input's (not clipped)."""
        return np.asarray(edges, np.float64) * self._scale() + np.array(self.offset * 2)

    def to_frame(self, edges: np.ndarray) -> np.ndarray:
        """Boxes ``(N, 4)`` x0, y0, x1, y1 in the input's pixels -> in the frame's, cut to the frame (what lay in
        the pad comes back as a zero-width or zero-height edge of the frame)."""
        ratio = np.array([self.frame[0] / self.scaled[0], self.frame[1] / self.scaled[1]] * 2)
        edges = (np.asarray(edges, np.float64) - np.array(self.offset * 2)) * ratio
        return np.clip(edges, 0.0, np.array(self.frame * 2, np.float64))
