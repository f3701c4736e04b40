"""Shared rendered data for the data tests: tiny images, few of them, rendered once per session."""

from __future__ import annotations

from pathlib import Path

import pytest

from popcode_trainer.data.render import render_builtin_split


@pytest.fixture(scope="session")
def builtin_split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Every built-in part, 3 grey 128x128 images each, some off-centre."""
    return render_builtin_split(tmp_path_factory.mktemp("builtin"), 3, random_position=True)
