"""OpenGL plumbing for rendering: headless EGL, pyrender's camera and pose conventions, depth at pixel centres.

PyOpenGL picks its platform when it is first imported; :func:`import_pyrender`
is the one place that imports pyrender and defaults it to EGL, so importing
popcode never changes the environment. :class:`DepthRenderer` renders depth as
the BOP toolkit does, for the metrics.
"""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError

PixelRegion = tuple[int, int, int, int]  # x0, y0, x1, y1 [px]: columns x0..x1-1, rows y0..y1-1
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera (y down, z forward) -> OpenGL (y up, z back)


def import_pyrender() -> Any:
    """pyrender, on headless EGL unless ``PYOPENGL_PLATFORM`` says otherwise (PyOpenGL reads it once, at import).

    pyglet, which pyrender imports for its viewer, is made headless too: otherwise it needs X11's libraries,
    which a server (a GPU machine, say) may not have.
    """
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ.setdefault("PYGLET_HEADLESS", "1")
    try:
        import pyrender
    except Exception as error:  # PyOpenGL raises assorted errors when no EGL library is present
        raise PopcodeError(_egl_help(error)) from error
    _warn_old_pyopengl()
    return pyrender


def _warn_old_pyopengl() -> None:
    """PyOpenGL before 3.1.7 (pyrender pins 3.1.0) cannot pass pointers on Python 3.12 and later: textured scenes
    fail deep inside it ("No array-type handler for type _ctypes.CArgObject")."""
    import OpenGL

    version = tuple(int(part) for part in OpenGL.__version__.split(".")[:3] if part.isdigit())
    if sys.version_info >= (3, 12) and version < (3, 1, 7):
        warnings.warn(f"PyOpenGL {OpenGL.__version__} cannot render scenes on Python "
                      f"{sys.version_info.major}.{sys.version_info.minor}: pip install 'PyOpenGL>=3.1.7' "
                      "(pyrender pins 3.1.0, which works up to Python 3.11)", stacklevel=3)


def _egl_help(error: BaseException) -> str:
    return (f"cannot start the offscreen OpenGL renderer ({type(error).__name__}: {error}). Install EGL and Mesa "
            "(e.g. apt-get install libegl1 libgl1-mesa-dri) and set PYOPENGL_PLATFORM=egl "
            f"(now {os.environ.get('PYOPENGL_PLATFORM')!r})")


def offscreen(width: int, height: int) -> Any:
    pyrender = import_pyrender()
    try:
        return pyrender.OffscreenRenderer(width, height)
    except Exception as error:
        raise PopcodeError(_egl_help(error)) from error


def delete_offscreen(renderer: Any) -> None:
    """Free an offscreen renderer's buffers and OpenGL context as ``OffscreenRenderer.delete`` does, without the
    ``gc.collect()`` it ends with: a walk of every object alive, up to a third of a second each time, which a demo
    paid for every renderer its renders and depth metrics closed (a quarter of a tiny demo's time). What the
    renderer leaves behind goes by reference counting or the collector's own passes."""
    renderer._platform.make_current()
    renderer._renderer.delete()
    renderer._platform.delete_context()
    renderer._renderer = renderer._platform = None


def pyrender_camera(pyrender: Any, K: np.ndarray, radius_mm: float, distance_mm: float,
                     opencv_pixel_centres: bool = True) -> Any:
    """The camera of ``K``; OpenGL samples pixel ``i`` at ``x = i + 0.5`` of the image plane.

    With ``opencv_pixel_centres`` the principal point is shifted so that pixel ``i``
    samples ``x = i``, OpenCV's pixel centre, where ``K`` projects a point: what
    training data needs, so that masks and boxes match the projected mesh (see
    ``tests/data/test_render_bop.py``). Without it ``K`` is used as given, as the
    BOP toolkit's renderer does, which its metrics (VSD) are defined with.
    """
    shift = 0.5 if opencv_pixel_centres else 0.0
    return pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + shift, K[1, 2] + shift,
                                     znear=max(distance_mm - radius_mm - 1.0, 1.0),
                                     zfar=distance_mm + radius_mm + 1.0)


def gl_pose(R_m2c: np.ndarray, t_m2c_mm: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R_m2c, t_m2c_mm
    return GL_FROM_CV @ pose


@contextlib.contextmanager
def _single_sample_framebuffers(pyrender: Any) -> Iterator[None]:
    """pyrender always renders into 4x multisampled buffers; make them single-sampled while a
    renderer sets up its framebuffer."""
    module = pyrender.renderer
    original = module.glRenderbufferStorageMultisample
    module.glRenderbufferStorageMultisample = lambda target, _samples, fmt, w, h: original(target, 0, fmt, w, h)
    try:
        yield
    finally:
        module.glRenderbufferStorageMultisample = original


def _linear_depth(window_z: np.ndarray, znear: float, zfar: float) -> np.ndarray:
    """Depth buffer values -> z [scene units], 0 where nothing is drawn (1.0, the far plane): pyrender's
    conversion, with its float32 arithmetic in its order, so that both give the same bits."""
    ndc_z = 2.0 * window_z - 1.0
    depth = (2.0 * znear * zfar) / (zfar + znear - ndc_z * (zfar - znear))
    depth[window_z == 1.0] = 0.0
    return depth


class CentreSampledDepth:
    """Depth sampled at pixel centres, as the BOP toolkit's renderer samples it.

    pyrender reads depth back from a 4x multisampled buffer as one sample's, off
    the pixel centre (on Mesa by (-0.125, +0.375) px, which moved masks, boxes and
    depth against the ground-truth pose). This renders its own ``scene`` single-
    sampled, with its own pyrender ``Renderer`` in the OpenGL context of
    ``offscreen``: a second context would die with the first (they share one EGL
    display), and a mesh's buffers belong to one renderer, hence the own scene.

    :meth:`render` can draw and read back one region of the image only: on a CPU
    rasteriser reading the whole framebuffer back costs more than drawing a part.
    """

    def __init__(self, offscreen: Any, width: int, height: int) -> None:
        self._pyrender = import_pyrender()
        from OpenGL import GL  # after import_pyrender: PyOpenGL picks its platform on its first import

        self._gl = GL
        self._platform = offscreen._platform  # pyrender has no public handle on its OpenGL context
        self._renderer = self._pyrender.Renderer(width, height)
        self._read_whole = self._renderer._read_main_framebuffer
        self._renderer._read_main_framebuffer = self._read_back  # pyrender's read-back, or the region's
        self.width, self.height = width, height
        self.scene = self._pyrender.Scene()
        self._framebuffer_ready = False
        self._region: PixelRegion | None = None

    def render(self, region: PixelRegion | None = None) -> np.ndarray:
        """Depth ``(H, W)`` float32 of ``scene`` [scene units], 0 where nothing is drawn.

        With ``region`` ``(x0, y0, x1, y1)`` [px, ends exclusive, inside the image] only that
        part, ``(y1 - y0, x1 - x0)``: equal to the same crop of the whole image, bit for bit,
        because the scissor test drops the fragments outside after rasterising exactly as
        for the whole image, and only the region is cleared and read back.
        """
        if region is not None:
            x0, y0, x1, y1 = region
            if not (0 <= x0 <= x1 <= self.width and 0 <= y0 <= y1 <= self.height):
                raise ValueError(f"region {region} is not inside the {self.width}x{self.height} image")
            if x0 == x1 or y0 == y1:
                return np.zeros((y1 - y0, x1 - x0), np.float32)
        flags = self._pyrender.RenderFlags.DEPTH_ONLY | self._pyrender.RenderFlags.OFFSCREEN
        self._platform.make_current()
        self._region = region
        try:
            if region is not None:
                self._gl.glEnable(self._gl.GL_SCISSOR_TEST)
                self._gl.glScissor(x0, self.height - y1, x1 - x0, y1 - y0)  # OpenGL's rows go up
            if not self._framebuffer_ready:
                with _single_sample_framebuffers(self._pyrender):
                    depth = self._renderer.render(self.scene, flags)
                self._framebuffer_ready = True
            else:
                depth = self._renderer.render(self.scene, flags)
        finally:
            self._gl.glDisable(self._gl.GL_SCISSOR_TEST)  # the context is shared with other renderers
            self._region = None
            self._platform.make_uncurrent()
        return depth.astype(np.float32)

    def _read_back(self, scene: Any, flags: Any) -> np.ndarray:
        """In place of pyrender's ``Renderer._read_main_framebuffer``: depth of the current region [scene units]."""
        if self._region is None:
            return self._read_whole(scene, flags)
        gl = self._gl
        x0, y0, x1, y1 = self._region
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, self._renderer._main_fb_ms)  # single-sampled: nothing to resolve
        window_z = gl.glReadPixels(x0, self.height - y1, x1 - x0, y1 - y0, gl.GL_DEPTH_COMPONENT, gl.GL_FLOAT)
        window_z = np.flip(np.frombuffer(window_z, np.float32).reshape(y1 - y0, x1 - x0), axis=0)
        camera = scene.main_camera_node.camera
        return _linear_depth(window_z, camera.znear, camera.zfar)

    def delete(self) -> None:
        self._platform.make_current()
        try:
            self._renderer.delete()
        finally:
            self._platform.make_uncurrent()


class DepthRenderer:
    """Depth images of one mesh as the BOP toolkit renders them for VSD.

    Like the toolkit's renderer: ``K`` as given (pixel ``i`` samples ``x = i + 0.5``),
    both faces of every triangle, one sample per pixel. ``opencv_pixel_centres``
    renders in the training renderer's convention instead (pixel ``i`` samples
    ``x = i``), which is how the depth of popcode's rendered splits is written.
    """

    def __init__(self, mesh_vertices_mm: np.ndarray, faces: np.ndarray, width: int, height: int,
                 opencv_pixel_centres: bool = False) -> None:
        self._opencv_pixel_centres = opencv_pixel_centres
        self._pyrender = import_pyrender()
        vertices = np.asarray(mesh_vertices_mm, dtype=np.float64)
        self._radius_mm = float(np.linalg.norm(vertices, axis=1).max())
        self.offscreen = offscreen(width, height)
        self._depth = CentreSampledDepth(self.offscreen, width, height)
        # pyrender culls back faces in depth-only passes whatever its flags say: every triangle
        # is drawn with both windings, so faces wound the wrong way are not lost.
        faces = np.asarray(faces)
        both_sides = trimesh.Trimesh(vertices, np.concatenate([faces, faces[:, ::-1]]), process=False)
        self._node = self._depth.scene.add(self._pyrender.Mesh.from_trimesh(both_sides, smooth=False))
        self._camera_node = None

    def render(self, K: np.ndarray, R_m2c: np.ndarray, t_m2c_mm: np.ndarray) -> np.ndarray:
        """Depth ``(H, W)`` float32 in mm along the camera z-axis, 0 where the object is absent."""
        t = np.asarray(t_m2c_mm, dtype=np.float64).reshape(3)
        scene = self._depth.scene
        if self._camera_node is not None:
            scene.remove_node(self._camera_node)
        camera = pyrender_camera(self._pyrender, np.asarray(K, dtype=np.float64), self._radius_mm, float(t[2]),
                                  self._opencv_pixel_centres)
        self._camera_node = scene.add(camera, pose=np.eye(4))
        scene.set_pose(self._node, gl_pose(np.asarray(R_m2c, dtype=np.float64), t))
        return self._depth.render()

    def close(self) -> None:
        self._depth.delete()
        delete_offscreen(self.offscreen)
