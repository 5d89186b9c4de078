"""``edit`` stage: a named edit applied to a trained model, rendered and scored (models/editing, models/metrics)."""
