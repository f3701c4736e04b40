"""``popcode run`` never mixes, duplicates or loses rows (issue 30): a resumed run gives exactly the uninterrupted
CSV or refuses in one line, whatever happened to its ``.partial``, its inputs or its ``--out``."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest

import popcode_runtime.inference.image_loop as image_loop
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.commands.cli import main
from popcode_runtime.commands.run_results import PartialResults
from popcode_trainer.data.render import render_builtin_split
from tools.fuzz_run import Pristine, fuzz_run, prepare
from tools.paths import SHIPPED_MODELS

SHIPPED = [str(path) for path in SHIPPED_MODELS]
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


def test_reordered_blocks_give_the_runs_order(split: Path, whole: Path, killed: bytes, tmp_path: Path) -> None:
    """Each image's block is whole and checked, so their order in the partial file does not matter: the results
    file lists the images in the run's order, as the uninterrupted run does."""
    out = tmp_path / "results.csv"
    partial = _resumable(killed, out)
    header, *body = _lines(partial)
    blocks, pending = [], []
    for line in body:
        pending.append(line)
        if line.startswith("#done"):
            blocks.append(pending)
            pending = []
    assert len(blocks) == KILLED_AT
    partial.write_text("\n".join([header, *(line for block in reversed(blocks) for line in block)]) + "\n")
    assert _run(split, out) == 0
    assert _rows(out) == _rows(whole)


def test_a_resumed_run_draws_every_image(split: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A picture is written before its image is closed, so a kill never leaves a finished image undrawn; a resume
    with another --draw (or none) is refused, not silently left without pictures."""
    out, pictures = tmp_path / "results.csv", tmp_path / "pictures"
    pictures.mkdir()
    _killed_run(split, out, "--draw", str(pictures))
    assert len(list(pictures.iterdir())) == KILLED_AT
    assert _run(split, out) == 2 and "other models, detections, split or options" in capsys.readouterr().err
    assert _run(split, out, "--draw", str(pictures)) == 0
    assert len(list(pictures.glob("*.png"))) == len(_rows(out)) - 1  # one image per part and row here


@pytest.mark.parametrize("kind", ["fifo", "symlink"])
def test_overwrite_never_replaces_what_is_not_a_regular_file(split: Path, whole: Path, tmp_path: Path, kind: str,
                                                             capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "results.csv"
    if kind == "fifo":
        os.mkfifo(out)
    else:
        out.symlink_to(whole)
    assert _run(split, out, "--overwrite") == 2
    assert "is not a regular file" in capsys.readouterr().err
    assert (out.is_fifo() if kind == "fifo" else out.is_symlink())


def test_a_detections_file_named_like_the_runs_lock_is_refused(split: Path, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture) -> None:
    detections = tmp_path / "results.csv.lock"
    detections.write_text("[]")
    code = main(["run", *SHIPPED, "--split", str(split), "--detections", str(detections), "--out",
                 str(tmp_path / "results.csv"), "--quiet"])
    assert code == 2 and "is the input" in capsys.readouterr().err and detections.read_text() == "[]"


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


def test_a_larger_partial_of_another_run_is_refused_as_another_runs(tmp_path: Path) -> None:
    """Another detector's many boxes make a partial larger than this run's few can be: the refusal names another
    run, not the size (issue 62)."""
    out = tmp_path / "results.csv"
    rows = [f"1,{im_id},1,0.5,1 0 0 0 1 0 0 0 1,0 0 500,0.01" for im_id in range(100)]
    out.with_name("results.csv.partial").write_text("\n".join(["#popcode-run " + "b" * 32, *rows]) + "\n")
    with pytest.raises(PopcodeError, match="holds the partial results of a run with other models, detections, "
                                           "split or options"):
        PartialResults(out, "a" * 32)
    assert not out.exists() and not out.with_name("results.csv.lock").exists()


def test_an_image_changed_in_place_to_the_same_size_is_refused(split: Path, killed: bytes, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """An image the killed run had done, mirrored and padded to its old size: resuming would mix its old rows with
    the new image's."""
    changed = tmp_path / "changed"
    shutil.copytree(split, changed)  # keeps the files' times: the killed run's fingerprint still matches the copy
    image = changed / "000001" / "gray" / "000000.png"
    data = image.read_bytes()
    pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    mirrored = cv2.imencode(".png", np.ascontiguousarray(pixels[:, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])[1]
    assert len(mirrored) <= len(data)
    image.write_bytes(mirrored.tobytes() + b"\0" * (len(data) - len(mirrored)))  # bytes after IEND are ignored
    out = tmp_path / "results.csv"
    _resumable(killed, out)
    capsys.readouterr()
    assert _run(changed, out) == 2
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
        assert "another popcode detect or run is writing" in err and err.count("\n") == 1
        assert not out.exists() and not out.with_name("results.csv.partial").exists()
    lock.unlink()
    assert _run(split, out) == 0  # once it is gone, the run goes through and leaves no lock behind
    assert _rows(out) == _rows(whole) and not lock.exists()


def test_an_image_of_another_runs_partial_is_refused_not_mixed_in(split: Path, killed: bytes, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """The same image and objects from a run with another decoder: its lines match their own checksum, but not
    this run's fingerprint."""
    other = _killed_run(split, tmp_path / "other.csv", "--decoder", "refined")
    other_lines, lines = _lines(other), killed.decode().splitlines()
    first_done = next(index for index, line in enumerate(lines) if line.startswith("#done"))
    assert other_lines[first_done].split()[:3] == lines[first_done].split()[:3]  # the same image
    out = tmp_path / "results.csv"
    _resumable(killed, out).write_text("\n".join([lines[0], *other_lines[1:first_done + 1], *lines[first_done + 1:]])
                                       + "\n")
    capsys.readouterr()
    assert _run(split, out) == 2
    err = capsys.readouterr().err
    assert "do not match their checksum" in err and err.count("\n") == 1, err


def _forge(partial: Path, column: int, value: str) -> None:
    """One field of the first closed image's first row changed and the image's checksum recomputed, as someone who
    read the format would: the checksum finds torn and careless edits, not these."""
    lines = _lines(partial)
    fields = lines[1].split(",")
    fields[column] = value
    lines[1] = ",".join(fields)
    done = next(index for index, line in enumerate(lines) if line.startswith("#done"))
    fingerprint = lines[0].removeprefix("#popcode-run ")
    checksum = hashlib.sha256("\n".join([fingerprint, *lines[1:done]]).encode()).hexdigest()[:16]
    lines[done] = " ".join([*lines[done].split(" ")[:3], checksum])
    partial.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(("column", "value"), [(3, "5.0"), (3, "-1.0"), (6, "-5.0"), (4, "1 0 0 0 1 0 0 0 2"),
                                               (4, "1 0 0 0 1 0 0 0 -1")],
                         ids=["score-5", "score-negative", "time-negative", "R-stretched", "R-reflection"])
def test_a_forged_row_of_values_popcode_never_writes_is_refused(split: Path, killed: bytes, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str], column: int,
                                                               value: str) -> None:
    out = tmp_path / "results.csv"
    _forge(_resumable(killed, out), column, value)
    capsys.readouterr()
    assert _run(split, out) == 2
    err = capsys.readouterr().err
    assert "holds values popcode never writes" in err and err.count("\n") == 1, err
    assert not out.exists()


def test_an_out_that_names_a_folder_is_refused_not_written_as_a_file(split: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["run", *SHIPPED, "--split", str(split), "--out", f"{tmp_path}/results/", "--quiet",
                 "--gt-boxes"]) == 2
    err = capsys.readouterr().err
    assert "names a folder" in err and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []


def test_an_out_onto_an_input_is_refused_even_with_its_partial_beside_it(split: Path, killed: bytes, tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """A partial file beside ``--out`` lets a run replace ``--out``; that must never be a file the run reads."""
    copied, models = tmp_path / "split", tmp_path / "models"
    shutil.copytree(split, copied)
    models.mkdir()
    model_paths = [shutil.copy(path, models) for path in SHIPPED]  # the same bytes: the killed run's fingerprint
    for out in (copied / "000001" / "scene_gt.json", copied / "results.csv", Path(model_paths[1])):
        before = out.read_bytes() if out.exists() else None
        _resumable(killed, out)
        capsys.readouterr()
        assert _run(copied, out, models=model_paths) == 2
        err = capsys.readouterr().err
        assert "an output never replaces or joins what the command reads" in err and err.count("\n") == 1, err
        assert (out.read_bytes() if out.exists() else None) == before


@contextlib.contextmanager
def _deadline(seconds: int) -> Iterator[None]:
    """A call still running after ``seconds`` fails the test (a FIFO read would otherwise hang it)."""
    def expire(signum: int, frame: object) -> None:
        pytest.fail(f"still running after {seconds} s")  # not TimeoutError: the CLI reports an OSError in one line

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize("what", ["partial-fifo", "partial-symlink-to-a-device", "partial-too-large", "lock-fifo"])
def test_a_partial_or_lock_no_run_wrote_is_refused_not_read(split: Path, killed: bytes, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str], what: str) -> None:
    """A FIFO would block the read forever and /dev/zero never end it; a partial file larger than the run's rows
    can be is no torn run's."""
    out = tmp_path / "results.csv"
    partial, lock = out.with_name("results.csv.partial"), out.with_name("results.csv.lock")
    if what == "partial-fifo":
        os.mkfifo(partial)
    elif what == "partial-symlink-to-a-device":
        partial.symlink_to("/dev/null")  # /dev/zero reads the same way, without end if the check is ever lost
    elif what == "lock-fifo":
        os.mkfifo(lock)
    else:
        with _resumable(killed, out).open("a") as handle:
            handle.write("1" * (1 << 20))  # a "torn last line" of 1 MiB
    capsys.readouterr()
    with _deadline(30):
        assert _run(split, out) == 2
    err = capsys.readouterr().err
    assert ("is not a regular file" in err or "larger than this run's results can be" in err) and \
        err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize("name", ["scene_camera.json", "notes.json"])
def test_a_split_json_file_that_is_a_fifo_is_refused_not_read(split: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str], name: str) -> None:
    """The run's fingerprint hashes each scene's JSON files; a FIFO among them would block that read forever."""
    copied = tmp_path / "split"
    shutil.copytree(split, copied)
    fifo = copied / "000002" / name
    fifo.unlink(missing_ok=True)
    os.mkfifo(fifo)
    capsys.readouterr()
    with _deadline(30):
        assert _run(copied, tmp_path / "results.csv") == 2
    err = capsys.readouterr().err
    assert "is not a regular file" in err and err.count("\n") == 1, err


@pytest.fixture(scope="module")
def pristine(split: Path, tmp_path_factory: pytest.TempPathFactory) -> Pristine:
    """What every fuzzed call starts from (each copies it): the split, its detections, killed and whole runs."""
    return prepare(tmp_path_factory.mktemp("pristine"), split)


def test_fuzzing_run_finds_nothing_unhandled(pristine: Pristine, tmp_path: Path) -> None:
    """30 random cases of popcode run on mutated detections, split files, images, partial files and options
    (tools/fuzz_run.py): each writes exactly the rows its inputs ask for (a resume: a fresh run's rows) or refuses
    in one line. A call that hangs is cut off by the fuzz's own watchdog and counted as unhandled, so no duration is
    asserted here."""
    report = fuzz_run(pristine, calls=30, seed=33, workdir=tmp_path)
    assert [(r.index, r.step, r.outcome, r.problem, r.done) for r in report.unhandled] == []
    assert report.outcomes["wrote results"] >= 5 and report.outcomes["refused"] >= 10  # both paths exercised
    assert report.outcomes["interrupted"] >= 1 and report.compared_with_fresh >= 1  # and a resume checked
    assert report.cases == 30 and report.calls >= 30  # every case ran its one or two calls


def test_a_fuzzed_call_that_hangs_is_cut_off_and_counted(pristine: Pristine, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The watchdog that replaces a timer in the test above: a call of popcode run still running at its limit (here
    every image read blocks) is cut off, recorded as a hang, which is unhandled, and the fuzz goes on."""
    monkeypatch.setattr(image_loop, "read_image", lambda *args, **kwargs: time.sleep(20))  # far past the limit
    report = fuzz_run(pristine, calls=3, seed=0, workdir=tmp_path, limit_s=0.5)  # cases 0 and 2 read images
    assert report.cases == 3 and report.outcomes["hang"] >= 1
    assert {r.outcome for r in report.unhandled} == {"hang"}
    assert all(r.problem.endswith("still running after 0.5 s") for r in report.unhandled)
