"""``python -m experiments.shipped_models``'s options (:mod:`tools.recipes`): what a refresh changes of the medium
recipe, and bad values refused before anything is rendered."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest
from user_commands import run_module

from popcode_trainer.demo.sizes import DEMO_SIZES
from tools.recipes import NETWORKS, shipped_arguments, shipped_size


def _args(**changes: object) -> argparse.Namespace:
    values = {"minutes": 30.0, "images": None, "scenes": None, "compile": "auto", "box_noise_p": None,
              "scene_share": None, "network": None, "traced_images": 0, "traced_share": 0.0, "init": None,
              "lr": None, "test_images": None}
    return argparse.Namespace(**{**values, **changes})


def test_defaults_are_the_medium_recipe_of_the_population_code_alone() -> None:
    medium = DEMO_SIZES["medium"].pipeline
    demo, size = shipped_size(_args())
    assert demo.minutes == 30.0
    assert size.representations == ("population_code",)
    assert size.config.data == medium.config.data
    assert (size.train_images_per_object, size.train_scenes) == (medium.train_images_per_object, medium.train_scenes)
    assert size.test_images_per_object == medium.test_images_per_object
    assert size.scene_share == medium.scene_share


def test_box_noise_share_and_data_changes_reach_the_config() -> None:
    medium = DEMO_SIZES["medium"].pipeline
    _, size = shipped_size(_args(box_noise_p=0.75, scenes=2400, images=100, test_images=3))
    assert size.config.data.box_noise_p == 0.75
    assert size.config.data.box_noise == medium.config.data.box_noise  # the preset stays the recipe's
    assert (size.train_images_per_object, size.train_scenes, size.test_images_per_object) == (100, 2400, 3)


def test_a_scene_share_changes_the_mix_alone() -> None:
    medium = DEMO_SIZES["medium"].pipeline
    _, size = shipped_size(_args(scene_share=0.5))
    assert size.scene_share == 0.5 != medium.scene_share
    assert (size.config, size.train_scenes) == (medium.config, medium.train_scenes)


def test_path_traced_images_and_their_share_reach_the_size_alone() -> None:
    medium = DEMO_SIZES["medium"].pipeline
    _, size = shipped_size(_args(traced_images=500, traced_share=0.25))
    assert (size.traced_train_images, size.traced_share) == (500, 0.25)
    assert (medium.traced_train_images, medium.traced_share) == (0, 0.0)
    assert (size.config, size.scene_share) == (medium.config, medium.scene_share)


def test_a_named_network_replaces_the_recipe_network_alone() -> None:
    medium = DEMO_SIZES["medium"].pipeline
    _, size = shipped_size(_args(network="small-x2"))
    assert size.config.network == NETWORKS["small-x2"]
    assert size.config.network != medium.config.network
    assert (size.config.data, size.config.train) == (medium.config.data, medium.config.train)


def test_a_start_and_a_rate_reach_the_training_settings_alone() -> None:
    """A fine-tune of a shipped model: its start (experiments.shipped_start) and a lower rate; nothing else."""
    medium = DEMO_SIZES["medium"].pipeline
    _, size = shipped_size(_args(init="start.pt", lr=3e-4))
    assert (size.config.train.init, size.config.train.lr) == ("start.pt", 3e-4)
    assert (medium.config.train.init, medium.config.train.lr) != ("start.pt", 3e-4)
    assert dataclasses.replace(size.config.train, init=medium.config.train.init, lr=medium.config.train.lr) == \
        medium.config.train
    assert (size.config.data, size.config.network) == (medium.config.data, medium.config.network)


@pytest.mark.parametrize("option", [["--lr", "0"], ["--lr", "2"], ["--lr", "nan"],
                                    ["--box-noise-p", "0"], ["--box-noise-p", "1.5"], ["--box-noise-p", "nan"],
                                    ["--scene-share", "0"], ["--scene-share", "1"], ["--scene-share", "nan"],
                                    ["--minutes", "0"], ["--network", "huge"], ["--test-images", "0"]])
def test_bad_values_exit_2(option: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        shipped_arguments(["--out", str(tmp_path / "out"), *option])
    assert stopped.value.code == 2
    assert option[0] in capsys.readouterr().err


def test_the_command_refuses_a_bad_value_before_any_file_is_written(tmp_path: Path) -> None:
    refused = run_module("experiments.shipped_models", "--out", tmp_path / "out", "--box-noise-p", "1.5", status=2)
    assert refused.stderr.strip().splitlines()[-1].endswith("--box-noise-p must lie in (0, 1], not 1.5")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_training_error_is_one_line_with_exit_2(tmp_path: Path) -> None:
    """Data too small for one batch: the trainer's error as one line, not a traceback; the renders stay."""
    refused = run_module("experiments.shipped_models", "--out", tmp_path / "out", "--images", "1", "--scenes", "1",
                         "--test-images", "1", "--group", "3", "--minutes", "1", status=2)
    err = refused.stderr
    last = err.strip().splitlines()[-1].split("\r")[-1]  # after the render's progress bar
    assert last.startswith("experiments.shipped_models: ") and "smaller than one batch" in last
    assert "Traceback" not in err
    assert (tmp_path / "out" / "train").is_dir()
