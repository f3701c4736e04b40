"""The one exception type the runtime raises for bad input or bad models, and the seam that makes it."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


class PopcodeError(ValueError):
    """Bad input, a bad model file or inconsistent metadata; the message says which.

    The command line prints the message as one line and exits non-zero.
    """


def first_line(error: BaseException) -> str:
    """The first non-empty line of an exception's message (libraries add pages of advice), or its type."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__


@contextmanager
def library_step(action: str) -> Iterator[None]:
    """Run a call into onnxruntime or OpenCV; whatever it raises becomes one line ``cannot <action>: <why>``.

    ``action`` names the step and the file, e.g. ``load model.onnx as an ONNX model``.

    The checks before such calls should leave nothing for this to catch; it is
    the backstop that keeps a library's own exception types and multi-line
    messages away from the user.
    """
    try:
        yield
    except PopcodeError:
        raise
    except MemoryError as error:
        raise PopcodeError(f"cannot {action}: out of memory") from error
    except Exception as error:  # the libraries raise their own types (cv2.error, onnxruntime's Fail, ...)
        raise PopcodeError(f"cannot {action}: {first_line(error)}") from error
