"""``render`` stage: a trained model rendered for the capture's test cameras and a novel path (models/rendering)."""
