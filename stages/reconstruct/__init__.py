"""``reconstruct`` stage: one Gaussian scene with path-traced reflections (models/reconstruction) -> model/."""
