"""What the experiments repeat: the seeds of the splits they render, and a recipe trained on rendered splits (resumed,
so that a run can be extended epoch budget by epoch budget) and then scored on a split it never saw.

The demo renders its training split with seed 0, its clean and cluttered test splits with 1000 and 2000 and its
training scenes with 3000 (``popcode_trainer.demo.steps``); the validation splits here use other seeds, so that no
recipe is chosen on the splits the demo reports.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from popcode_trainer.data.box_noise import box_noise_preset
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.eval.pipeline.detector_boxes import with_detector_boxes
from popcode_trainer.eval.pipeline.evaluate import MethodResult, evaluate_models
from popcode_trainer.eval.pipeline.models import methods_from_paths
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.train.config import Config
from popcode_trainer.train.loop import train
from popcode_trainer.train.run_files import LAST_CHECKPOINT, read_metrics
from popcode_trainer.train.training_data import TrainingData

TRAIN_SEED = 0  # as the demo's training split (and, + 3000, its training scenes)
VALIDATION_SEED = 2000  # clean single parts (budget_curve, precision); the demo's 2000 renders cluttered scenes
CLUTTERED_VALIDATION_SEED, CLEAN_VALIDATION_SEED = 4000, 5000  # scene_mix's two validation splits


def training_config(base: Config, run_dir: Path, epochs: int, **data: Any) -> Config:
    """``base`` training for ``epochs`` into ``run_dir``, with the ``data`` settings given (the splits, their weights,
    the models folder) replaced; the rest of the recipe as it is."""
    changed = replace(base, data=replace(base.data, **data),
                      train=replace(base.train, out_dir=str(run_dir), epochs=epochs))
    return Config.from_dict(changed.to_dict())


def train_run(config: Config, data: TrainingData) -> None:
    """Train ``config`` on ``data`` into its ``train.out_dir``, resuming the run found there: ``train.epochs`` may
    grow on resume, so a longer budget costs only the epochs it adds."""
    run_dir = Path(config.train.out_dir)
    train(config, data.representation, data.train_set, data.val_set, resume=(run_dir / LAST_CHECKPOINT).exists(),
          val_instances=data.val_instances)


def score_last_checkpoint(run_dir: Path, method: str, split_dir: Path, obj_ids: Sequence[int],
                          boxes: str = "none") -> MethodResult:
    """The run's last checkpoint scored (as ``method``, rotation only, no VSD) on a rendered split, with its
    ground-truth boxes or crops cut from boxes of the box-noise preset ``boxes``."""
    split = read_eval_split([split_dir], split_dir / BUILTIN_MODELS_FOLDER, obj_ids)
    if boxes != "none":
        split = with_detector_boxes(split, box_noise_preset(boxes))
    methods = methods_from_paths([run_dir / LAST_CHECKPOINT], [method])
    return evaluate_models(methods, split, vsd=False, progress=False)[0]


def training_so_far(run_dir: Path) -> dict[str, float]:
    """Seconds of the training loop and crops seen over the epochs run so far, and the last epoch's
    median error on the images the run held out of its training split (up to symmetry)."""
    metrics = read_metrics(run_dir, ("seconds", "samples_per_s", "val_error_median_deg"))
    return {"training_s": sum(metrics["seconds"].tolist()),
            "crop_updates": int(round(sum((metrics["samples_per_s"] * metrics["seconds"]).tolist()))),
            "held_out_median_deg": round(float(metrics["val_error_median_deg"][-1]), 2)}
