"""What the trainer reports as written survives a power cut, not only a killed process (issue 66): a checkpoint, an
exported model and a metrics row are synced before their rename and their folder after it (``power_cut``)."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import onnx
import pytest
import torch
from power_cut import PowerCut

from popcode_runtime.base.files import temporary_name
from popcode_runtime.coding.population_code import CodeLayout
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.data import render
from popcode_trainer.export.onnx_export import export_onnx
from popcode_trainer.train import checkpoint
from popcode_trainer.train.epoch_record import append_metrics
from popcode_trainer.train.network import NetworkConfig, PopcodeNet
from popcode_trainer.train.run_files import EpochMetrics


def test_a_checkpoint_survives_a_power_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cut = PowerCut().install(monkeypatch)
    path = tmp_path / "run" / "last.pt"
    checkpoint.save_atomic({"epoch": 3, "weights": torch.arange(5.0)}, path)
    assert cut.survivor(path) == path.read_bytes(), "the checkpoint is lost or empty after a power cut"
    state = torch.load(io.BytesIO(cut.survivor(path)), weights_only=True)
    assert state["epoch"] == 3 and torch.equal(state["weights"], torch.arange(5.0))
    assert cut.unsafe_renames() == []


def test_an_exported_model_survives_a_power_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = NetworkConfig(output_dim=42 * 12, conv_channels=(8, 8, 8), squeeze_channels=4, hidden=(32, 32, 32))
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE,
                             code=CodeLayout(n_axes=42, n_angles=12, sigma_deg=30.0), objects={1: {"diameter": 100.0}})
    cut = PowerCut().install(monkeypatch)
    path = export_onnx(PopcodeNet(config).eval(), metadata, tmp_path / "model.onnx")
    survivor = cut.survivor(path)
    assert survivor == path.read_bytes(), "the model is lost or empty after a power cut"
    onnx.checker.check_model(onnx.load_from_string(survivor))
    assert cut.unsafe_renames() == []


def test_every_metrics_row_survives_a_power_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The row is written before the checkpoint, so a row lost while its checkpoint survives would leave a
    resumed run's log short of an epoch it trained."""
    cut = PowerCut().install(monkeypatch)
    path = tmp_path / "metrics.csv"
    for epoch in (1, 2):
        append_metrics(path, EpochMetrics(epoch, 0.5, 0.4, 10.0, 8.0, 100.0, 30.0))
    assert cut.survivor(path) == path.read_bytes(), "rows are lost after a power cut"
    assert path.read_text().count("\n") == 3  # header and two rows
    assert cut.unsafe_renames() == []


def test_a_checkpoint_save_removes_what_a_dead_writer_left(tmp_path: Path) -> None:
    """A save killed mid-write (or cut by the power) leaves its temporary file; the next save removes it, and
    leaves that of a writer still running."""
    path = tmp_path / "last.pt"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True).stdout.strip()
    left = Path(str(temporary_name(path)).replace(f".{os.getpid()}-", f".{dead}-"))
    running = Path(str(temporary_name(path)).replace(f".{os.getpid()}-", f".{os.getppid()}-"))
    left.write_bytes(b"half a checkpoint")
    running.write_bytes(b"another run's checkpoint, being written")
    checkpoint.save_atomic({"epoch": 1}, path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, running.name])


@pytest.mark.parametrize("syncfs", [True, False], ids=["syncfs", "fsync-each-file"])
def test_a_rendered_image_marked_done_survives_a_power_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                            syncfs: bool) -> None:
    """A render renames its images unsynced and syncs them in batches (the per-file syncs cost it a third of its
    time): a cut right after any record is written, even one after the file system wrote back that record but
    not its images, must find every image that a record marks done whole (a record read back empty marks nothing
    done: ``test_a_record_read_back_empty_is_rendered_again``)."""
    cut = PowerCut().install(monkeypatch, syncfs=syncfs)
    monkeypatch.setattr(render, "RECORD_BATCH", 2)  # several batches in a small split
    real_write_json = render.write_json_atomic
    checked = []

    def write_record_then_cut(path: Path, data: object, batch: object = None) -> None:
        real_write_json(path, data, batch)
        if path.parent.name == render.RECORDS_FOLDER:
            checked.append(_done_images_survive(cut, tmp_path / "split"))

    monkeypatch.setattr(render, "write_json_atomic", write_record_then_cut)
    render.render_builtin_split(tmp_path / "split", 5, size=(64, 64), obj_ids=[1])
    assert checked and all(checked), "an image marked done was lost or empty after a power cut"
    records = sorted((tmp_path / "split" / "000001" / render.RECORDS_FOLDER).glob("*.json"))
    assert len(records) == 5 and all(cut.survivor(record) == record.read_bytes() for record in records)


def _done_images_survive(cut: PowerCut, split: Path) -> bool:
    """Whether, after a power cut now that finds every record written, the picture, depth and mask each one marks
    done are whole though none of them was written back unsynced."""
    scene = split / "000001"
    for record in (scene / render.RECORDS_FOLDER).glob("*.json"):
        if cut.survivor(record, journal_committed=True, written_back=True) is None:
            continue
        for image in (scene / "gray" / f"{record.stem}.png", scene / "depth" / f"{record.stem}.png",
                      scene / "mask_visib" / f"{record.stem}_000000.png"):
            if cut.survivor(image, journal_committed=True) != image.read_bytes():
                return False
    return True


def test_a_stopped_render_keeps_the_images_it_finished(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Images wait for their batch's sync before their records are written; a render stopped mid-batch (Ctrl-C, an
    error) still writes the records of those it finished, so a rerun does not render them again."""
    real_render_one, rendered = render._render_one, []

    def stop_after_three(*arguments: object) -> None:
        if len(rendered) == 3:
            raise KeyboardInterrupt
        real_render_one(*arguments)
        rendered.append(arguments[3])

    monkeypatch.setattr(render, "_render_one", stop_after_three)
    with pytest.raises(KeyboardInterrupt):
        render.render_builtin_split(tmp_path / "split", 6, size=(64, 64), obj_ids=[1])
    records = sorted(path.stem for path in (tmp_path / "split" / "000001" / render.RECORDS_FOLDER).glob("*.json"))
    assert records == [f"{im_id:06d}" for im_id in rendered]


def test_a_record_read_back_empty_is_rendered_again(tmp_path: Path) -> None:
    split = render.render_builtin_split(tmp_path / "split", 3, size=(64, 64), obj_ids=[1])
    record = split / "000001" / render.RECORDS_FOLDER / "000001.json"
    whole = record.read_bytes()
    record.write_bytes(b"")  # what a power cut before the batch's commit can leave
    assert not render.image_done(record)
    render.render_builtin_split(tmp_path / "split", 3, size=(64, 64), obj_ids=[1])
    assert record.read_bytes() == whole
