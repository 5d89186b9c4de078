"""``poses`` stage: photos -> COLMAP poses (models/poses) -> a capture with SfM points."""
