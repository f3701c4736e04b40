"""What a training run's folder holds, by name: the trainer writes these files; demo, export and figures read them."""

LAST_CHECKPOINT = "last.pt"  # written after every epoch; --resume continues from it
BEST_CHECKPOINT = "best.pt"  # the epoch with the lowest validation error
METRICS_FILE = "metrics.csv"  # one row per epoch (train.EpochMetrics)
MODEL_FILE = "model.onnx"  # the exported float model; quantised ones beside it as model.<kind>.onnx
CROP_CACHE_FOLDER = "crop_cache"  # the decoded training crops (data.crop_cache); safe to delete
