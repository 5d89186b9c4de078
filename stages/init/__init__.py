"""``init`` stage: the initial Gaussians of a capture (models/initialisation) -> init/points.ply."""
