"""A predicted population code beside the code it was trained towards, for one ground-truth instance (the
paper's Figs. 1 and 5); reporting draws the pair (:func:`popcode_trainer.eval.reporting.figures.plot_instance_code`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.population_code import CodeLayout
from popcode_runtime.geometry.crop import read_image
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.model.metadata import Representation

from ...data.bop import Instance
from ...train.representations import representation_from_metadata


@dataclass(frozen=True)
class InstanceCode:
    """The runtime's code of one instance and its training target, on the model's code layout."""

    layout: CodeLayout
    predicted: np.ndarray  # (layout.size,)
    target: np.ndarray  # (layout.size,)
    title: str  # which instance it is


def instance_code(estimator: PoseEstimator, instance: Instance) -> InstanceCode:
    """What the runtime predicts for one ground-truth instance beside the code it was trained towards."""
    metadata = estimator.metadata
    if metadata.representation != Representation.POPULATION_CODE:
        raise PopcodeError(f"the code figure needs a population-code model, this one is {metadata.representation}")
    prediction = estimator.predict(read_image(instance.image_path), [instance.box], K=instance.K,
                                   obj_ids=[instance.obj_id], return_code=True)[0]
    target = representation_from_metadata(metadata).target(instance)
    title = f"object {instance.obj_id}, scene {instance.scene_id} image {instance.im_id}"
    return InstanceCode(metadata.code, prediction.code, target, title)
