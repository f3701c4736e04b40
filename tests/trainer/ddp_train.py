"""Entry point for the subprocess tests (torchrun, kill-and-resume): the tiny run on synthetic data.

    python ddp_train.py OUT_DIR EPOCHS [--resume]
"""

from __future__ import annotations

import sys
from pathlib import Path

from tiny import tiny_config, tiny_data, tiny_representation

from popcode_trainer.train.loop import train

if __name__ == "__main__":
    config = tiny_config(Path(sys.argv[1]), epochs=int(sys.argv[2]))
    representation = tiny_representation(config)
    train(config, representation, *tiny_data(representation), resume="--resume" in sys.argv[3:])
