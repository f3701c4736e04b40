"""Entry point for the torchrun test: the tiny run, on the synthetic data, in every rank."""

from __future__ import annotations

import sys
from pathlib import Path

from popcode_trainer.train import train
from tiny import tiny_config, tiny_data, tiny_representation

if __name__ == "__main__":
    config = tiny_config(Path(sys.argv[1]), epochs=2)
    representation = tiny_representation(config)
    train(config, representation, *tiny_data(representation))
