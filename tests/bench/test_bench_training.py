"""Smoke tests of the speed benchmarks ``python -m bench.training`` and ``python -m bench.scene_render`` run as a
user runs them at tiny sizes: the JSON contract and the table rows; never timings."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from user_commands import run_module


@pytest.mark.parametrize(("flags", "chosen"), [(frozenset(), "eager-nchw-fp32"),
                                               (frozenset({"avx512_bf16"}), "eager-nchw-bf16")])
@pytest.mark.slow
def test_training_throughput_smoke(flags: frozenset[str], chosen: str, tmp_path: Path) -> None:
    # 30 images a part leave 108 training crops of parts 3-6, the 96 that --quick's batches need; the bench's 2000
    # would render 12000 images for rows this test only checks the shape of. The path is chosen as on a CPU
    # without / with native bf16; a process of its own starts with the C library's allocator defaults.
    run_module("bench.training", "--quick", "--images", "30", "--networks", "tiny", "--threads", "1", "--workers",
               "0", "1", "--paths", "eager-nchw-fp32", "eager-cl-bf16", "--out", tmp_path, cpu_flags=flags)
    payload = json.loads((tmp_path / "training.json").read_text(encoding="utf-8"))
    rows = payload["rows"]
    assert payload["arguments"].startswith("--quick --images 30 ")
    parts = [(r["part"], r["workers"]) for r in rows]
    assert parts == [("data", 0), ("data", 1), ("forward_backward", None), ("optimizer", None),
                     ("path: eager-nchw-fp32", None), ("path: eager-cl-bf16", None),
                     (f"path: {chosen}", None), ("step", 0), ("step", 1), ("loop", 0)]
    # the chosen path again once freed memory is kept, as training runs; the plain rows before it with the defaults
    assert [r["memory_kept"] for r in rows] == [False] * 6 + [True] * 4
    loop = rows[-1]  # the training loop itself; --quick: two epochs, the second beside a plain eager step
    assert len(loop["epoch_crops_per_s"]) == len(loop["plain_crops_per_s"]) == 1
    assert loop["vs_plain_eager"] == pytest.approx(loop["epoch_crops_per_s"][0] / loop["plain_crops_per_s"][0])
    assert loop["crops_per_s"] == pytest.approx(loop["epoch_crops_per_s"][0])
    assert all(not r["fell_back"] and r["first_s"] > 0 for r in rows if r["part"].startswith("path"))
    assert all("NCHW" in r["path"] for r in rows if r["part"] == "step")  # tiny widths of 4: NCHW (fast_path)
    assert all(r["network"] == "tiny" and r["threads"] == 1 and r["crops_per_s"] > 0 for r in rows)
    table = (tmp_path / "training.md").read_text(encoding="utf-8")
    assert sum(line.startswith("| tiny |") for line in table.splitlines()) == len(rows)
    assert "cpu_flags" in payload["machine"]


def test_scene_render_prints_speed_and_visibility_and_writes_the_picture(tmp_path: Path) -> None:
    picture = tmp_path / "scene.jpg"
    printed = run_module("bench.scene_render", "--scenes", "2", "--size", "64", "48", "--picture", picture).stdout
    payload = json.loads(printed)
    assert payload["scenes"] == 2 and payload["instances"] > 0 and payload["scenes_per_s"] > 0
    assert sum(payload["instances_per_visibility_bin"].values()) == payload["instances"]
    assert picture.is_file() and picture.stat().st_size > 0
