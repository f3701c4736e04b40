"""What a depth camera does to depth: axial noise growing with distance, flying pixels and dropouts at depth edges,
holes on steep and on dark surfaces, quantisation.

The scene renderer applies it to the rendered depth after every annotation is computed from the exact depth
(masks and visibility are ground truth, not measurements), so the split's ``depth/`` holds what a sensor would
deliver, as a real BOP test split's does, and VSD and any depth-based estimate meet holes and noise.

The model, per pixel of the exact depth ``z`` [mm] (0: nothing seen, stays 0), in this order:

1. *Edges.* A pixel whose 3x3 neighbourhood spans a depth jump larger than ``edge_jump_fraction * z`` lies on a
   depth edge; so does every pixel within ``edge_width_px - 1`` of one. There it is lost with probability
   ``edge_dropout_p`` (a structured-light camera's occlusion shadow, a rejected ambiguous code) or, with
   probability ``flying_pixel_p``, reads a random mix of the nearest and farthest surface within ``edge_width_px``
   (a "flying pixel": a time-of-flight pixel or a correlation window straddling the edge averages both).
2. *Axial noise.* Gaussian with ``sigma(z) = axial_sigma_floor_mm + axial_sigma_per_m2_mm * (z / 1 m)**2``:
   triangulation turns a constant disparity error into a depth error growing with ``z**2``.
3. *Quantisation.* A triangulating sensor measures disparity in steps, so its depth steps grow with ``z**2``
   (``disparity_step_at_1m_mm``, the step at 1 m); then the sensor's output unit (``output_step_mm``). Writing
   the split quantises once more, to the depth format's step (``depth_scale``).
4. *Holes.* The chance of no measurement rises linearly from 0 at the incidence angle (surface normal against
   the camera ray) ``hole_angle_deg[0]`` to 1 at ``hole_angle_deg[1]``: too little light returns from a steep
   surface. On a dark surface it is ``dark_hole_p`` times how far its brightness lies below ``dark_level``
   (linear intensity of the rendered colour, a proxy for how much of the sensor's own light comes back). Holes
   come in patches of about ``hole_patch_px``, as a real sensor's do: a smoothed random field, uniform at each
   pixel, is thresholded at the pixel's hole probability.

Every random draw comes from the generator passed in, in a fixed order, so a seeded generator gives the same
result.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from popcode_runtime.base.errors import PopcodeError

from .sensor import DISPLAY_GAMMA, sensor_preset

MM_PER_M = 1000.0
GREY_TO_LINEAR = ((np.arange(256) / 255.0) ** DISPLAY_GAMMA).astype(np.float32)  # display grey -> linear


@dataclass(frozen=True)
class DepthNoise:
    """One depth sensor's imperfections; see the module docstring for what each parameter does."""

    axial_sigma_floor_mm: float = 0.0  # sigma of the depth noise close to the camera
    axial_sigma_per_m2_mm: float = 0.0  # sigma added at 1 m, growing with distance squared
    edge_jump_fraction: float = 0.02  # a jump beyond this fraction of the distance is a depth edge
    edge_width_px: int = 1  # how far from a depth jump a pixel is disturbed
    edge_dropout_p: float = 0.0  # an edge pixel is lost
    flying_pixel_p: float = 0.0  # an edge pixel reads a mix of the near and the far surface
    hole_angle_deg: tuple[float, float] = (90.0, 90.0)  # incidence angles between which holes grow from 0 to all
    dark_level: float = 0.0  # linear brightness below which the returned light gets too weak; 0: never
    dark_hole_p: float = 0.0  # chance of a hole on a black surface
    hole_patch_px: float = 0.0  # size of a hole patch (smoothing of the hole field); 0: single pixels
    disparity_step_at_1m_mm: float = 0.0  # depth step of the disparity quantisation at 1 m; 0: none
    output_step_mm: float = 0.0  # the sensor's depth unit; 0: not quantised

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            for number in value if isinstance(value, tuple) else (value,):
                if isinstance(number, bool) or not isinstance(number, numbers.Real) or not np.isfinite(number) \
                        or number < 0:
                    raise PopcodeError(f"depth noise {field.name} must be a finite number >= 0, got {value!r}")
            if field.name.endswith("_p") and value > 1:
                raise PopcodeError(f"depth noise {field.name} is a probability (0 to 1), got {value}")
        if self.edge_dropout_p + self.flying_pixel_p > 1:
            raise PopcodeError(f"depth noise edge_dropout_p + flying_pixel_p must be at most 1, got "
                               f"{self.edge_dropout_p} + {self.flying_pixel_p}")
        if not isinstance(self.edge_width_px, numbers.Integral) or self.edge_width_px < 1:
            raise PopcodeError(f"depth noise edge_width_px must be a whole number >= 1, got {self.edge_width_px!r}")
        if self.edge_jump_fraction <= 0:
            raise PopcodeError(f"depth noise edge_jump_fraction must be above 0, got {self.edge_jump_fraction}")
        if len(self.hole_angle_deg) != 2 or not self.hole_angle_deg[0] <= self.hole_angle_deg[1] <= 90:
            raise PopcodeError(f"depth noise hole_angle_deg needs (low, high) with 0 <= low <= high <= 90, got "
                               f"{self.hole_angle_deg}")
        if self.dark_level > 1:
            raise PopcodeError(f"depth noise dark_level is a linear brightness (0 to 1), got {self.dark_level}")

    def axial_sigma_mm(self, z_mm: np.ndarray) -> np.ndarray:
        """Standard deviation [mm] of the axial noise at depth ``z_mm`` [mm]."""
        return self.axial_sigma_floor_mm + self.axial_sigma_per_m2_mm * (np.asarray(z_mm) / MM_PER_M) ** 2


# Keyed by the names of sensor.SENSOR_PRESETS: the depth camera beside each image preset. README "Sensor effects".
DEPTH_NOISE_PRESETS: dict[str, DepthNoise | None] = {
    "none": None,  # exact rendered depth
    # An industrial structured-light camera (phase-shift patterns, e.g. Zivid, Photoneo class).
    "industrial": DepthNoise(
        axial_sigma_floor_mm=0.03,  # vendors' point precision is tens of micrometres at close range
        axial_sigma_per_m2_mm=0.15,  # about 0.1 mm at 0.7 m, 0.2 mm at 1 m: their data sheets' order
        edge_width_px=1,  # a focused projector and camera: one pixel either side of an edge
        edge_dropout_p=0.5,  # where projector or camera cannot see the edge, its code is rejected
        flying_pixel_p=0.05,  # few mixed codes survive the decoder's checks
        hole_angle_deg=(70.0, 88.0),  # an HDR exposure still reads fairly steep metal and plastic
        dark_level=0.02, dark_hole_p=0.3,  # HDR exposure reads all but nearly black surfaces
        hole_patch_px=2.0,  # small patches: high-resolution decoding
    ),
    # The depth stream of a Primesense/Kinect-v1-like structured-light camera (T-LESS's Primesense).
    "webcam": DepthNoise(
        axial_sigma_floor_mm=0.7,  # least-squares fit over 0.5-2 m of Nguyen et al. 2012's
        axial_sigma_per_m2_mm=1.3,  # Kinect model sigma = 1.2 mm + 1.9 mm/m^2 * (z - 0.4 m)^2
        edge_width_px=2,  # its correlation window smears edges over about two pixels
        edge_dropout_p=0.5,  # the projector's occlusion shadow beside every near edge
        flying_pixel_p=0.2,  # a window straddling an edge matches a depth in between
        hole_angle_deg=(60.0, 82.0),  # Nguyen et al.: its noise rises steeply beyond about 60 degrees
        dark_level=0.05, dark_hole_p=0.8,  # dark (IR-absorbing) surfaces return too few speckles
        hole_patch_px=3.0,  # its depth is computed on coarse windows: holes come in blobs
        disparity_step_at_1m_mm=2.9,  # 1/8-pixel disparity at f 580 px and a 75 mm baseline
        output_step_mm=1.0,  # OpenNI delivers whole millimetres
    ),
    # A phone's time-of-flight / LiDAR depth.
    "phone": DepthNoise(
        axial_sigma_floor_mm=2.0,  # a few millimetres at arm's length: low-power emitter, small pixels
        axial_sigma_per_m2_mm=4.0,  # about 6 mm at 1 m, 2 cm at 2 m as the return weakens
        edge_width_px=2,  # a low-resolution depth map upsampled to the image
        edge_dropout_p=0.2,  # confidence filtering drops some edge pixels
        flying_pixel_p=0.6,  # a ToF pixel straddling an edge averages both returns: the classic mixed pixel
        hole_angle_deg=(65.0, 85.0),  # the return falls with the cosine of the incidence angle
        dark_level=0.04, dark_hole_p=0.6,  # a weak emitter gets too little back from dark surfaces
        hole_patch_px=3.0,  # confidence masks drop patches, not single pixels
        output_step_mm=1.0,  # Android's DEPTH16 format holds whole millimetres
    ),
}


def depth_noise_preset(name: str) -> DepthNoise | None:
    """The depth noise of sensor preset ``name``; None for exact depth."""
    sensor_preset(name)  # one place names the presets and refuses an unknown one
    return DEPTH_NOISE_PRESETS[name]


def linear_brightness(rgb: np.ndarray) -> np.ndarray:
    """Linear intensity ``(H, W)`` float32 in [0, 1] of a rendered ``(H, W, 3)`` uint8 colour image (display values)."""
    return GREY_TO_LINEAR[cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)]


def _slope(depth_mm: np.ndarray, axis: int) -> np.ndarray:
    """Depth change [mm/px] along ``axis`` (0: rows, 1: columns) to the neighbour whose depth is nearer this
    pixel's: the slope of the pixel's own surface, not of the jump across a depth edge."""
    step = np.diff(depth_mm, axis=axis)
    first, last = (step[:1], step[-1:]) if axis == 0 else (step[:, :1], step[:, -1:])
    forward = np.concatenate([step, last], axis=axis)
    backward = np.concatenate([first, step], axis=axis)
    return np.where(np.abs(forward) <= np.abs(backward), forward, backward)


def incidence_angle_deg(depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Angle [deg] between the surface normal and the camera ray at each pixel of ``depth_mm`` ``(H, W)`` [mm].

    ``K`` is the 3x3 camera matrix (OpenCV pixel centres). The surface ``z(u, v) * (x, y, 1)`` with
    ``x = (u - cx) / fx``, ``y = (v - cy) / fy`` has the normal ``(-fx z_u, -fy z_v, fx z_u x + fy z_v y + z)``,
    whose dot product with the ray ``(x, y, 1)`` is ``z``; the slopes ``z_u``, ``z_v`` are taken on the pixel's
    own side of a depth edge. 90 where there is no surface.
    """
    depth_mm = np.asarray(depth_mm, np.float32)
    height, width = depth_mm.shape
    x = ((np.arange(width) - K[0, 2]) / K[0, 0]).astype(np.float32)[None, :]
    y = ((np.arange(height) - K[1, 2]) / K[1, 1]).astype(np.float32)[:, None]
    along_x = np.float32(K[0, 0]) * _slope(depth_mm, 1)
    along_y = np.float32(K[1, 1]) * _slope(depth_mm, 0)
    normal_sq = along_x**2 + along_y**2 + (along_x * x + along_y * y + depth_mm) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = depth_mm / np.sqrt(normal_sq * (x**2 + y**2 + 1.0))
    return np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=0.0), 0.0, 1.0)))


def _uniform_field(rng: np.random.Generator, shape: tuple[int, int], patch_px: float) -> np.ndarray:
    """Uniform [0, 1) at every pixel, correlated over about ``patch_px``: thresholded, it gives patches."""
    field = rng.standard_normal(shape, dtype=np.float32)
    if patch_px > 0:
        field = cv2.GaussianBlur(field, (0, 0), patch_px, borderType=cv2.BORDER_REFLECT)
        field /= max(float(field.std()), 1e-12)
    return ndtr(field)


def _quantise(z_mm: np.ndarray, noise: DepthNoise) -> np.ndarray:
    """``z_mm`` float32 (0: no value) on the sensor's disparity steps, then in its output unit."""
    if noise.disparity_step_at_1m_mm > 0:
        steps_mm = np.float32(MM_PER_M**2 / noise.disparity_step_at_1m_mm)  # depth = steps_mm / disparity
        with np.errstate(divide="ignore"):
            disparity = np.round(steps_mm / z_mm)  # 0 where z is 0 or beyond the last disparity step
            z_mm = np.where(disparity > 0, steps_mm / disparity, np.float32(0.0))
    if noise.output_step_mm > 0:
        step_mm = np.float32(noise.output_step_mm)
        z_mm = np.round(z_mm / step_mm) * step_mm
    return z_mm


def _edge_pixels(depth_mm: np.ndarray, rng: np.random.Generator, noise: DepthNoise) -> tuple[np.ndarray, np.ndarray]:
    """Depth with flying pixels at depth edges, and the edge pixels lost ``(H, W)`` bool (step 1 of the model)."""
    valid = depth_mm > 0
    unseen_far = np.where(valid, depth_mm, np.float32(np.inf))  # no surface: never the nearest
    neighbours = np.ones((3, 3), np.uint8)
    jump = cv2.dilate(depth_mm, neighbours) - cv2.erode(unseen_far, neighbours) > noise.edge_jump_fraction * depth_mm
    edge = cv2.dilate((jump & valid).astype(np.uint8), np.ones((2 * noise.edge_width_px - 1,) * 2, np.uint8)) > 0
    rows, cols = np.nonzero(edge & valid)
    draw, mix = rng.random((2, len(rows)), dtype=np.float32)
    lost = np.zeros(depth_mm.shape, bool)
    lost[rows, cols] = draw < noise.edge_dropout_p
    flying = (draw >= noise.edge_dropout_p) & (draw < noise.edge_dropout_p + noise.flying_pixel_p)
    rows, cols, mix = rows[flying], cols[flying], mix[flying]
    window = np.ones((2 * noise.edge_width_px + 1,) * 2, np.uint8)
    near, far = cv2.erode(unseen_far, window)[rows, cols], cv2.dilate(depth_mm, window)[rows, cols]
    observed = depth_mm.copy()
    observed[rows, cols] = near + mix * (far - near)
    return observed, lost


def _hole_probability(depth_mm: np.ndarray, K: np.ndarray, rgb: np.ndarray, noise: DepthNoise) -> np.ndarray:
    """Chance ``(H, W)`` that a pixel has no measurement: a steep or a dark surface (step 4 of the model)."""
    low_deg, high_deg = noise.hole_angle_deg
    steep_p = np.clip((incidence_angle_deg(depth_mm, K) - low_deg) / max(high_deg - low_deg, 1e-6), 0.0, 1.0)
    if noise.dark_level == 0:
        return steep_p
    dark_p = noise.dark_hole_p * np.clip(1.0 - linear_brightness(rgb) / noise.dark_level, 0.0, 1.0)
    return 1.0 - (1.0 - steep_p) * (1.0 - dark_p)


def apply_depth_noise(depth_mm: np.ndarray, K: np.ndarray, rgb: np.ndarray, rng: np.random.Generator,
                      noise: DepthNoise) -> np.ndarray:
    """The exact depth ``(H, W)`` [mm] (0: nothing seen) as the sensor would measure it: float32 [mm], 0 = no value.

    ``K``: the 3x3 camera matrix; ``rgb``: the rendered ``(H, W, 3)`` uint8 colour, whose brightness decides
    where a surface is too dark to measure.
    """
    depth_mm = np.asarray(depth_mm, np.float32)
    if rgb.shape[:2] != depth_mm.shape:
        raise PopcodeError(f"colour {rgb.shape[:2]} and depth {depth_mm.shape} differ in size")
    observed, lost = _edge_pixels(depth_mm, rng, noise)
    observed += noise.axial_sigma_mm(observed).astype(np.float32) * rng.standard_normal(depth_mm.shape,
                                                                                        dtype=np.float32)
    observed = _quantise(np.where((depth_mm > 0) & (observed > 0), observed, np.float32(0.0)), noise)
    lost |= _uniform_field(rng, depth_mm.shape, noise.hole_patch_px) < _hole_probability(depth_mm, K, rgb, noise)
    return np.where(lost, np.float32(0.0), observed).astype(np.float32)
