"""Train a detector: epochs over the frames, a checkpoint after each (a rerun resumes from it), a validation
loss, progress on the terminal and, when asked, an epoch count fitted to a time budget after the first epoch and
again after the second.

The rate warms up over the first epoch and then falls on a cosine to zero at the last, so the first epoch is
the same whatever the run's length: a time budget can be fitted from it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import append_synced, csv_text, write_bytes_atomic
from popcode_runtime.base.output_lock import OutputLock

from ..train.checkpoint import load, restore_rng_state, rng_state, save_atomic
from .averaging import WeightAverage
from .config import DetectorConfig
from .frames import FrameSet, collate, held_out, read_frames
from .network import build_detector
from .start import apply_start, resolve_detector_start

CHECKPOINT = "detector.pt"
METRICS = "metrics.csv"
LOCK = "detector.lock"
METRIC_COLUMNS = ("epoch", "train_loss", "val_loss", "seconds", "lr")
FIT_EPOCHS = 2  # a time budget's epochs are fitted after each of the first two (fitted_epochs)


@dataclass(frozen=True)
class DetectorRun:
    """A finished (or resumed and finished) training: where its checkpoint is and what it learnt on."""

    checkpoint: Path
    config: DetectorConfig
    obj_ids: tuple[int, ...]
    epochs_run: int  # in this call
    first_epoch_seconds: float | None  # this call's first epoch, for a time budget
    start: str  # which first weights the run took (detection/start.py), in words


def fitted_epochs(seconds: float, epoch_seconds: Sequence[float], most: int) -> int:
    """Epochs that fill ``seconds`` after the ones timed (``epoch_seconds``), the rest at the fastest of them.

    Fitted after each of the first :data:`FIT_EPOCHS`: a first epoch slowed by whatever shared the cores then
    once fitted 9 epochs where the budget held 70 (2 s an epoch after a 15 s first, the quick demo's 150 s).
    The rate's cosine barely moves at the second epoch, so the refit does not distort it.
    """
    done, spent = len(epoch_seconds), sum(epoch_seconds)
    rest = int(max(seconds - spent, 0.0) / max(min(epoch_seconds), 1e-9))
    return max(done, 1, min(most, done + rest))


def learning_rate(config: DetectorConfig, progress: float) -> float:
    """The rate at ``progress`` epochs into the run: linear warm-up over the first, cosine to zero after."""
    if progress < 1.0:
        return config.lr * max(progress, 0.02)
    rest = (progress - 1.0) / max(config.epochs - 1.0, 1e-9)
    return config.lr * 0.5 * (1.0 + math.cos(math.pi * min(rest, 1.0)))


def _epoch_loss(model: torch.nn.Module, loader: DataLoader, optimizer: torch.optim.Optimizer | None,
                config: DetectorConfig, epoch: int, bar: tqdm | None, average: WeightAverage | None = None) -> float:
    """One pass over ``loader``: training when ``optimizer`` is given (``average`` updated after each step), else
    the validation loss (batch norm frozen, no gradients). torchvision's FCOS returns its losses only in training
    mode."""
    model.train()
    if optimizer is None:
        for module in model.modules():
            if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                module.eval()
    total, count = 0.0, 0
    for step, (images, targets) in enumerate(loader):
        if optimizer is not None:
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(config, epoch + step / len(loader))
        with torch.set_grad_enabled(optimizer is not None):
            losses = model(images, targets)
            loss = sum(losses.values())
        if not torch.isfinite(loss):
            raise PopcodeError(f"the detector's loss became {loss.item()} in epoch {epoch + 1}: lower lr")
        if optimizer is not None:
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            optimizer.step()
            if average is not None:
                average.update(model)
        total, count = total + loss.item() * len(images), count + len(images)
        if bar is not None:
            bar.update(len(images))
            bar.set_postfix(loss=f"{total / count:.3f}")
    return total / max(count, 1)


def train_detector(splits: Sequence[str | Path], obj_ids: Sequence[int], out_dir: str | Path,
                   config: DetectorConfig, seconds: float | None = None, progress: bool = True) -> DetectorRun:
    """Train (or resume) a detector of ``obj_ids`` on the scene ``splits`` into ``out_dir``.

    A new run starts from the start ``config.init`` names (:mod:`popcode_trainer.detection.start`), said in
    one line; the checkpoint keeps that line, so a resumed run reports the start it took.

    ``seconds``: fit the epochs so that training takes about that long (within 1 and ``config.epochs``): from the
    first epoch's time, then again after the second from the faster of the two (:func:`fitted_epochs`). A run
    folder holding another config's checkpoint is refused; one holding this config's resumes after its last
    finished epoch.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with OutputLock(out_dir / LOCK, f"another process is training a detector into {out_dir} (it holds {LOCK}); "
                                    "wait for it to end, or give another folder"):
        obj_ids = tuple(sorted(obj_ids))
        checkpoint = out_dir / CHECKPOINT
        state = load(checkpoint) if checkpoint.exists() else None
        if state is not None:  # a fitted run keeps its fitted epochs
            config = _resumed_config(state, config, obj_ids, checkpoint, keep_epochs=seconds is not None)
        # a start named wrongly is refused before the frames are read
        first_weights, start_line = resolve_detector_start(config) if state is None else \
            (None, str(state.get("start", "unknown (a run of an older trainer)")))
        train_frames, val_frames = held_out(read_frames(splits, obj_ids, config), config.val_fraction, config.seed)
        train_set = FrameSet(train_frames, config, augment=True, progress=progress)
        val_set = FrameSet(val_frames, config, augment=False, progress=progress)
        model = build_detector(config, len(obj_ids))
        if first_weights is not None:
            apply_start(model, first_weights)
        if progress and state is None:
            print(f"detector: first weights from {start_line}", flush=True)
        optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        start = 0
        if state is not None:
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            restore_rng_state(state["rng"])
            start = int(state["epoch"])
        else:
            _truncate_metrics(out_dir / METRICS)
        average = WeightAverage(model, config.ema_decay, None if state is None else state.get("ema")) \
            if config.ema_decay else None
        first_seconds, epoch, fit_times, most_epochs = None, start, [], config.epochs
        while epoch < config.epochs:
            started = time.perf_counter()
            train_set.epoch = epoch
            generator = torch.Generator().manual_seed(config.seed * 100_003 + epoch)
            loader = DataLoader(train_set, config.batch_size, shuffle=True, collate_fn=collate, generator=generator,
                                drop_last=len(train_set) > config.batch_size)
            with tqdm(total=len(loader) * config.batch_size, desc=f"detector epoch {epoch + 1}/{config.epochs}",
                      unit="img", disable=not progress, leave=False) as bar:
                train_loss = _epoch_loss(model, loader, optimizer, config, epoch, bar, average)
            validated = model if average is None else average.model  # the weights the export takes
            val_loss = _epoch_loss(validated, DataLoader(val_set, config.batch_size, collate_fn=collate), None,
                                   config, epoch, None) if len(val_set) else math.nan
            took = time.perf_counter() - started
            epoch += 1
            first_seconds = took if first_seconds is None else first_seconds
            if seconds is not None and start == 0 and epoch <= FIT_EPOCHS:
                fit_times.append(took)
                config = replace(config, epochs=fitted_epochs(seconds, fit_times, most_epochs))
            save_atomic({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "epoch": epoch,
                         "start": start_line, **({} if average is None else {"ema": average.state()}),
                         "config": config.to_dict(), "obj_ids": list(obj_ids), "rng": rng_state(),
                         "frames": {"train": len(train_set), "val": len(val_set),
                                    "splits": [str(Path(s)) for s in splits]}}, checkpoint)
            _append_metrics(out_dir / METRICS, [epoch, train_loss, val_loss, took,
                                                learning_rate(config, epoch - 1e-9)])
            if progress:
                tqdm.write(f"detector epoch {epoch}/{config.epochs}: train loss {train_loss:.4f}, "
                           f"val loss {val_loss:.4f}, {took:.0f} s")
        return DetectorRun(checkpoint, config, obj_ids, epoch - start, first_seconds, start_line)


def _resumed_config(state: dict, config: DetectorConfig, obj_ids: tuple[int, ...], path: Path,
                    keep_epochs: bool) -> DetectorConfig:
    """The checkpoint's config, its epochs raised to ``config``'s unless ``keep_epochs``; any other difference is
    refused in one line."""
    saved = DetectorConfig.from_dict(state["config"])
    changed = saved.differences(config)
    if changed or tuple(state["obj_ids"]) != obj_ids:
        what = ", ".join(changed) if changed else f"objects {list(state['obj_ids'])} now {list(obj_ids)}"
        raise PopcodeError(f"{path} was trained with other settings ({what}): give another folder or delete it "
                           "to start over")
    return saved if keep_epochs else replace(saved, epochs=max(saved.epochs, config.epochs))


def _truncate_metrics(path: Path) -> None:
    write_bytes_atomic(path, csv_text([METRIC_COLUMNS]).encode())


def _append_metrics(path: Path, row: list[float]) -> None:
    append_synced(path, csv_text([[f"{v:.6g}" if isinstance(v, float) else v for v in row]]),
                  first=csv_text([METRIC_COLUMNS]))
