"""Training and scoring the buffer network: ``config.py`` (TrainConfig), ``data.py`` (readers and batches),
``train.py`` (accelerate loop, exact resume), ``evaluate.py`` (per-buffer accuracy against trivial baselines)."""
