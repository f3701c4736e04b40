"""``popcode run`` never mixes, duplicates or loses rows (issue 30): a resumed run gives exactly the uninterrupted
CSV or refuses in one line, whatever happened to its ``.partial``, its inputs or its ``--out``."""

from __future__ import annotations

import fcntl
import shutil
from collections.abc import Callable
from pathlib import Path

import onnx
import pytest

import popcode_runtime.image_loop as image_loop
from popcode_runtime.cli import main
from popcode_trainer.data.render import render_builtin_split

MODELS = Path(__file__).resolve().parents[2] / "models"
SHIPPED = [str(MODELS / "builtin-parts-1-2.onnx"), str(MODELS / "builtin-parts-3-6.onnx")]
KILLED_AT = 4  # images a killed run closes


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The six built-in parts, 2 images each, in 160 x 120 images."""
    return render_builtin_split(tmp_path_factory.mktemp("trust") / "split", 2, size=(160, 120), random_position=True)


@pytest.fixture(scope="module")
def killed(split: Path, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """The ``.partial`` a killed run of the shipped models leaves (copied into each test's own ``--out``)."""
    return _killed_run(split, tmp_path_factory.mktemp("killed") / "results.csv").read_bytes()


def _resumable(killed: bytes, out: Path) -> Path:
    partial = out.with_name(out.name + ".partial")
    partial.write_bytes(killed)
    return partial


@pytest.fixture(scope="module")
def whole(split: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("whole") / "whole.csv"
    assert _run(split, out) == 0
    return out


def _run(split: Path, out: Path, *options: str, models: list[str] = SHIPPED) -> int:
    return main(["run", *models, "--split", str(split), "--out", str(out), "--quiet", "--gt-boxes", *options])


def _rows(path: Path) -> list[str]:
    return [line.rsplit(",", 1)[0] for line in path.read_text().splitlines()]


def _killed_run(split: Path, out: Path, *options: str, models: list[str] = SHIPPED) -> Path:
    """A run interrupted after :data:`KILLED_AT` images; its ``.partial``."""
    calls = {"n": 0}
    real_read = image_loop.read_image

    def killed(path: Path, *args: object) -> object:
        calls["n"] += 1
        if calls["n"] == KILLED_AT + 1:
            raise KeyboardInterrupt
        return real_read(path, *args)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(image_loop, "read_image", killed)
        assert _run(split, out, *options, models=models) == 130
    partial = out.with_name(out.name + ".partial")
    assert partial.read_text().count("#done") == KILLED_AT
    return partial


def _lines(partial: Path) -> list[str]:
    return partial.read_text().splitlines()


def _tear_last_mark(partial: Path) -> None:
    text = partial.read_text().rstrip("\n")
    partial.write_text(text[:-5])  # the last mark's checksum cut short


def _retarget_last_mark(partial: Path) -> None:
    lines = _lines(partial)
    scene, image, checksum = lines[-1].split()[1:]
    lines[-1] = f"#done {scene} {int(image) + 1} {checksum}"  # a torn write that still reads as another image
    partial.write_text("\n".join(lines) + "\n")


def _half_of_the_last_image(partial: Path) -> None:
    text = partial.read_text()
    partial.write_text(text[:text.rindex("#done")] + "2,1,3,0.5,1 0")


@pytest.mark.parametrize("tear", [_tear_last_mark, _retarget_last_mark, _half_of_the_last_image],
                         ids=["checksum-cut", "mark-names-another-image", "half-written-rows"])
def test_a_torn_tail_is_redone_not_duplicated(split: Path, whole: Path, killed: bytes, tmp_path: Path,
                                              tear: Callable[[Path], None]) -> None:
    out = tmp_path / "results.csv"
    tear(_resumable(killed, out))
    assert _run(split, out) == 0
    assert _rows(out) == _rows(whole)


def _edit_a_number(partial: Path) -> None:
    lines = _lines(partial)
    fields = lines[1].split(",")
    fields[3] = "0.999"
    lines[1] = ",".join(fields)
    partial.write_text("\n".join(lines) + "\n")


def _garbage_row(partial: Path) -> None:
    lines = _lines(partial)
    partial.write_text("\n".join([lines[0], "not,a,row", *lines[1:]]) + "\n")


def _row_of_another_image(partial: Path) -> None:
    lines = _lines(partial)
    fields = lines[1].split(",")
    fields[1] = "77"
    partial.write_text("\n".join([lines[0], ",".join(fields), *lines[1:]]) + "\n")


def _invalid_utf8(partial: Path) -> None:
    data = partial.read_bytes()
    partial.write_bytes(data[:60] + b"\xff\xfe" + data[60:])


def _image_closed_twice(partial: Path) -> None:
    lines = _lines(partial)
    first_image = lines[1:lines.index(next(line for line in lines if line.startswith("#done"))) + 1]
    partial.write_text("\n".join([*lines, *first_image]) + "\n")


@pytest.mark.parametrize(("tamper", "message"), [
    (_edit_a_number, "do not match their checksum"),
    (_garbage_row, "do not match their checksum"),
    (_row_of_another_image, "do not match their checksum"),
    (_invalid_utf8, "is not text"),
    (_image_closed_twice, "closed twice"),
], ids=["edited-number", "garbage-row", "row-of-another-image", "invalid-utf8", "closed-twice"])
def test_a_changed_partial_is_refused_in_one_line(split: Path, killed: bytes, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str], tamper: Callable[[Path], None],
                                                  message: str) -> None:
    out = tmp_path / "results.csv"
    partial = _resumable(killed, out)
    tamper(partial)
    before = partial.read_bytes()
    capsys.readouterr()
    assert _run(split, out) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not out.exists() and partial.read_bytes() == before  # nothing lost either


def test_another_split_or_max_images_is_refused(split: Path, killed: bytes, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "results.csv"
    _resumable(killed, out)
    other = render_builtin_split(tmp_path / "other", 2, size=(160, 120), random_position=True, seed=5)
    changed = tmp_path / "changed"
    shutil.copytree(split, changed)
    image = next((changed / "000004" / "gray").iterdir())
    image.write_bytes(image.read_bytes() + b"\0")  # one image's file changed
    capsys.readouterr()
    for argv in ((other, out), (changed, out), (split, out, "--max-images", "6")):
        assert _run(*argv) == 2
        assert "other models, detections, split or options" in capsys.readouterr().err


def test_changed_external_weights_are_refused(split: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    models = tmp_path / "models"
    models.mkdir()
    external = []
    for path in SHIPPED:
        target = models / Path(path).name
        onnx.save_model(onnx.load(path), target, save_as_external_data=True, location=f"{target.stem}.weights",
                        size_threshold=0)
        external.append(str(target))
    out = tmp_path / "results.csv"
    _killed_run(split, out, models=external)
    weights = models / "builtin-parts-3-6.weights"
    data = bytearray(weights.read_bytes())
    data[len(data) // 2] ^= 0xFF
    weights.write_bytes(bytes(data))
    capsys.readouterr()
    assert _run(split, out, models=external) == 2
    assert "other models, detections, split or options" in capsys.readouterr().err


def test_a_second_run_on_one_out_is_refused_while_the_first_writes(split: Path, whole: Path, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "results.csv"
    lock = out.with_name("results.csv.lock")
    with lock.open("a") as held:  # what a running `popcode run` holds
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert _run(split, out) == 2
        err = capsys.readouterr().err
        assert "another popcode run is writing" in err and err.count("\n") == 1
        assert not out.exists() and not out.with_name("results.csv.partial").exists()
    lock.unlink()
    assert _run(split, out) == 0  # once it is gone, the run goes through and leaves no lock behind
    assert _rows(out) == _rows(whole) and not lock.exists()
