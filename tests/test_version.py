"""One version for both halves, kept in runtime/popcode_runtime/VERSION."""

import importlib.metadata
from pathlib import Path

import popcode_runtime
import popcode_trainer

VERSION_FILE = Path(__file__).resolve().parents[1] / "runtime" / "popcode_runtime" / "VERSION"


def test_both_packages_report_the_version_file() -> None:
    text = VERSION_FILE.read_text(encoding="utf-8").strip()
    assert popcode_runtime.__version__ == popcode_trainer.__version__ == text
    assert importlib.metadata.version("popcode-runtime") == text
