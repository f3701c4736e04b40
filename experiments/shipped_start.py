"""A start of a shipped model's own weights, so that a refresh fine-tunes it instead of training from scratch.

    python -m experiments.shipped_start MODEL.onnx --split TRAIN [--split TRAIN_SCENES ...] --out START.pt
        [--crops 512] [--seed 0]

The shipped models keep no checkpoint: their weights are read back from the ONNX file
(:func:`popcode_trainer.export.read_back.read_back`; use a float or fp16 copy, the static int8 copy holds its
weights rounded), each BatchNorm fitted to ``--crops`` instances drawn from the training splits, as the runtime
crops them. The start carries the output layer too, so it fits only a run of the same parts and code
(``experiments.shipped_models --init START.pt``). How far the rebuilt network is from the file is measured on the
same crops and written to the start's card (largest output difference, share of equal argmax neurons).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from bench.agreement import split_crops
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.export.read_back import read_back
from popcode_trainer.train.pretrained import OUTPUT_MODULE, POSE_START, TRANSFERRED_MODULES, network_shape, save_start
from tools.command import bad_input_exits


def training_crops(estimator: PoseEstimator, splits: Sequence[Path], count: int, seed: int) -> np.ndarray:
    """``count`` runtime crops of the model's objects (instances at least 60 % visible, as training takes them),
    drawn evenly from each split."""
    rng = np.random.default_rng(seed)
    crops = []
    for split in splits:
        instances = read_eval_split([split], split / "models", sorted(estimator.metadata.objects),
                                    min_visib_fract=0.6).instances
        if not instances:
            raise PopcodeError(f"{split}: no instance of the model's objects {sorted(estimator.metadata.objects)}")
        chosen = rng.choice(len(instances), size=min(len(instances), count // len(splits)), replace=False)
        crops.append(split_crops(estimator, [instances[i] for i in sorted(chosen)])[0])
    return np.concatenate(crops)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path, help="a popcode ONNX model (float or fp16 weights)")
    parser.add_argument("--split", type=Path, action="append", required=True, help="a training split (repeatable)")
    parser.add_argument("--out", type=Path, required=True, help="the start file to write")
    parser.add_argument("--crops", type=int, default=512, help="crops fitting the BatchNorms (default 512)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.crops < 2 * len(args.split):
        parser.error(f"--crops must be at least two a split, not {args.crops}")
    with bad_input_exits("experiments.shipped_start"):
        estimator = PoseEstimator(args.model)
        crops = training_crops(estimator, args.split, args.crops, args.seed)
        model, metadata = read_back(args.model, crops)
        with torch.no_grad():
            rebuilt = model(torch.from_numpy(crops)).numpy()
        reference = estimator.run(crops)
        agreement = {"max_output_difference": float(np.abs(rebuilt - reference).max()),
                     "argmax_agreement": float((rebuilt.argmax(1) == reference.argmax(1)).mean()),
                     "crops": len(crops)}
        state = {name: tensor.detach().clone() for name, tensor in model.state_dict().items()
                 if name.split(".")[0] in (*TRANSFERRED_MODULES, OUTPUT_MODULE)}
        training = metadata.training
        card = {"epochs": training.get("epochs"), "commit": str(training.get("git_revision", "?"))[:7],
                "from_model": str(args.model), "model_sha256": hashlib.sha256(args.model.read_bytes()).hexdigest(),
                "code": metadata.code.to_dict() if metadata.code else None, "objects": sorted(metadata.objects),
                "read_back": agreement,
                "batch_norm_fitted_on": [str(split) for split in args.split]}
        save_start(POSE_START, network_shape(model.config), state, args.out, card)
    print(f"{args.out}: {len(state)} tensors of {args.model} (output difference at most "
          f"{agreement['max_output_difference']:.4f}, argmax equal on {100 * agreement['argmax_agreement']:.1f} % "
          f"of {len(crops)} crops)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
