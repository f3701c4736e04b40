"""Rendering warns, naming the fix, where PyOpenGL is too old for the Python it runs on."""

from __future__ import annotations

import types
import warnings

import OpenGL
import pytest

from popcode_trainer.data import gl


@pytest.mark.parametrize(("python", "pyopengl", "warns"), [
    ((3, 12, 0), "3.1.0", True),
    ((3, 13, 1), "3.1.6", True),
    ((3, 12, 0), "3.1.7", False),
    ((3, 12, 0), "3.1.10", False),
    ((3, 11, 9), "3.1.0", False),
])
def test_old_pyopengl_on_new_python(monkeypatch: pytest.MonkeyPatch, python: tuple[int, int, int], pyopengl: str,
                                    warns: bool) -> None:
    monkeypatch.setattr(gl, "sys", types.SimpleNamespace(version_info=_Version(python)))
    monkeypatch.setattr(OpenGL, "__version__", pyopengl)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gl._warn_old_pyopengl()
    messages = [str(w.message) for w in caught]
    assert bool(messages) == warns
    if warns:
        assert "pip install 'PyOpenGL>=3.1.7'" in messages[0] and pyopengl in messages[0]


class _Version(tuple):
    """A stand-in for ``sys.version_info``: a tuple with ``major`` and ``minor``."""

    @property
    def major(self) -> int:
        return self[0]

    @property
    def minor(self) -> int:
        return self[1]
