"""Smoke test of ``python -m bench.representations --smoke``: every file and table shape, no timing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from user_commands import run_module


@pytest.mark.slow
def test_tiny_run_writes_every_table(tmp_path: Path) -> None:
    run_module("bench.representations", "--smoke", "--out", tmp_path)

    record = json.loads((tmp_path / "representations.json").read_text())
    assert record["size"] == "smoke" and record["object_groups"] == [[1, 2], [3, 4, 5, 6]]
    methods = record["results"]["methods"]
    assert list(methods) == ["population_code", "population_code (refined)", "single_variable", "one_hot",
                             "multi_hypothesis"]
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
