"""Inference: ``PoseEstimator`` (crop -> engine -> decode -> camera frame), the per-image loop over a split and
the latency benchmark. Imports every room below the commands."""
