"""``export`` stage: a trained model as a standard 3DGS PLY for common splat viewers (models/gaussians/export.py)."""
