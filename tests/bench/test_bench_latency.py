"""Smoke test of ``python -m bench.latency --quick`` run as a user runs it: the JSON contract and the table rows;
never timings."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from user_commands import run_module

LATENCY_FIELDS = {"variant", "network", "batch", "threads", "stage", "median_ms", "p90_ms", "p99_ms", "floor_ms",
                  "compute_floor_ms"}
QUANTISED = {"int8-static", "nbits4", "nbits8"}  # the quantised variants bench.latency measures beside fp32
LATENCY_BATCHES = {1, 8, 32}


@pytest.mark.slow
def test_latency_writes_the_contract(tmp_path: Path) -> None:
    run_module("bench.latency", "--quick", "--networks", "tiny", "--out", tmp_path)
    payload = json.loads((tmp_path / "latency.json").read_text(encoding="utf-8"))
    assert {"cpu", "cores", "onnxruntime", "torch"} <= set(payload["machine"])
    records = payload["records"]
    for record in records:
        assert set(record) >= LATENCY_FIELDS
        assert record["stage"] in ("end-to-end", "inference")
        assert ("argmax_agreement" in record) == (record["variant"] in QUANTISED)
        assert ("pose_agreement" in record) == (record["variant"] in QUANTISED)
        if "pose_agreement" in record:  # the same argmax is the same pose
            assert 0.0 <= record["argmax_agreement"] <= record["pose_agreement"] <= 1.0
    variants = {r["variant"] for r in records}
    assert variants == {"fp32", "torch-eager", *QUANTISED}
    assert {r["batch"] for r in records} == LATENCY_BATCHES
    assert any(r["threads"] == 1 for r in records)
    # Every runtime variant has both stages at every batch; torch eager has inference only.
    runtime_rows = [r for r in records if r["variant"] != "torch-eager"]
    assert len(runtime_rows) == 4 * len(LATENCY_BATCHES) * 2 * len({r["threads"] for r in records})
    assert all({"output_layer_share", "conv_share"} <= set(r) for r in runtime_rows
               if r["batch"] == 1 and r["stage"] == "inference")
    assert set(payload["gemm_peak_gmac_s"]) == {f"{t} {kind}" for t in {r["threads"] for r in records}
                                               for kind in ("fp32", "int8")}
    assert set(payload["networks"][0]["decode_ms"]) == {"argmax", "refined"}
    table = (tmp_path / "latency.md").read_text(encoding="utf-8")
    summary_rows = len(QUANTISED) + 2  # batch 1, 1 thread: fp32, the quantised variants, torch eager
    assert sum(line.startswith("| tiny |") for line in table.splitlines()) == summary_rows + len(records) + 1
