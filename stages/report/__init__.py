"""Reports: per-scene and batch HTML (stages.report.scene, stages.report.batch)."""
