"""``evaluate`` stage: metrics.json of renders against the capture's test split (models/metrics)."""
