"""Checkpoints through the runtime's pipeline with the torch engine: every option the ONNX model has."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic import K
from trained import pasted_frame, trained_checkpoint

from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.model.metadata import RotationFrame
from popcode_trainer.eval.pipeline.models import load_model
from popcode_trainer.export.onnx_export import export_checkpoint


@pytest.mark.filterwarnings("ignore:no mesh")  # translation from the 3-D box corners is what is compared
def test_a_checkpoint_predicts_what_its_export_predicts_with_top_k_refined_and_translation(tmp_path: Path) -> None:
    ckpt, crops = trained_checkpoint(tmp_path, rotation_frame=RotationFrame.ALLOCENTRIC)
    onnx_path = export_checkpoint(ckpt, tmp_path / "model.onnx", crops)[0].path
    frame, boxes = pasted_frame()
    options = {"K": K, "top_k": 3, "translation": True}
    checkpoint = load_model(ckpt, decoder="refined").estimator
    exported = PoseEstimator(onnx_path, decoder="refined")
    for a, b in zip(exported.predict(frame, boxes, **options), checkpoint.predict(frame, boxes, **options),
                    strict=True):
        np.testing.assert_allclose(b.R_m2c, a.R_m2c, atol=1e-4)
        np.testing.assert_allclose(b.t_m2c_mm, a.t_m2c_mm, rtol=1e-4)
        assert len(b.hypotheses) == len(a.hypotheses) >= 1
        for h_b, h_a in zip(b.hypotheses, a.hypotheses, strict=True):
            np.testing.assert_allclose(h_b.R_m2c, h_a.R_m2c, atol=1e-4)
    assert checkpoint.decoder == "refined" and checkpoint.providers == []
