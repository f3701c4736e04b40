"""Where the shipped models and the numbers lie, named once for the benchmarks, experiments, fuzzers and tests
(no torch here: the fuzzers need the runtime only)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODELS_DIR = ROOT / "models"
SHIPPED_1_2 = MODELS_DIR / "builtin-parts-1-2.onnx"
SHIPPED_3_6 = MODELS_DIR / "builtin-parts-3-6.onnx"
SHIPPED_MODELS = (SHIPPED_1_2, SHIPPED_3_6)
SHIPPED_DETECTOR = MODELS_DIR / "builtin-parts-detector.onnx"
RESULTS = ROOT / "bench" / "results"  # one place for the numbers of benchmarks, experiments and fuzzers alike
