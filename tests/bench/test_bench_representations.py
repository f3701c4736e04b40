"""Smoke test of bench/representations.py at a tiny size: every file and table shape, no timing."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from popcode_trainer.pipeline import PipelineSize

BENCH = Path(__file__).resolve().parents[2] / "bench" / "representations.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_representations", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_tiny_run_writes_every_table(bench, tmp_path: Path) -> None:
    size = PipelineSize(train_images_per_object=4, test_images_per_object=1, epochs=1, n_axes=42, n_angles=12,
                        sigma_deg=30.0, network={"conv_channels": [4, 4, 4], "squeeze_channels": 2,
                                                 "hidden": [16, 16, 16]},
                        batch_size=4, num_hypotheses=4)
    bench.run_benchmark(size, tmp_path, "smoke")

    record = json.loads((tmp_path / "representations.json").read_text())
    assert record["object_groups"] == [[1, 2], [3, 4, 5, 6]]
    methods = record["results"]["methods"]
    assert list(methods) == ["population_code", bench.REFINED, "single_variable", "one_hot", "multi_hypothesis"]
    for method in methods.values():
        assert list(method["groups"]) == ["Without ambiguity", "With ambiguity", "All objects"]
        assert sorted(method["per_object"]) == ["1", "2", "3", "4", "5", "6"]
        assert len(method["models"]) == 2
    assert set(record["machine"]) >= {"cpu", "cores", "onnxruntime", "torch"}
    assert record["paper"]["table_iv_percent"]["All objects"]["Population Code"] == [74.22, 84.70, 83.46, 87.31]
    markdown = (tmp_path / "representations.md").read_text()
    assert markdown.count("| population_code (refined) |") >= 9  # 3 groups + 6 per-object tables (+ symmetry)
    assert "**All objects** (paper)" in markdown
    assert (tmp_path / "eval" / "errors_multi_hypothesis.csv").is_file()
    assert [Path(p).name for p in record["code_figures"]] == ["code_obj1.png", "code_obj3.png"]
    assert all(Path(p).read_bytes()[:4] == b"\x89PNG" for p in record["code_figures"])
