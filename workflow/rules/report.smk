rule report:
    """Self-contained HTML report of one scene: ground truth vs ours per layer, error maps, training curves,
    metrics, cost, what the scene required and what was switched off, edits."""
    input:
        unpack(report_inputs),
    output:
        f"{RESULTS}/{{scene}}/report.html",
    params:
        py=PY,
        cfg=lambda wc: json.dumps(scene_config(wc.scene), sort_keys=True),
        folder=lambda wc: f"{RESULTS}/{wc.scene}",
    log:
        f"{RESULTS}/{{scene}}/logs/report.log",
    shell:
        "{params.py} -m stages.report scene {params.folder} --config-json {params.cfg:q} --out {output} > {log} 2>&1"


rule batch_report:
    """Scenes side by side like the paper's Tables 1 (PSNR diffuse / specular / final) and 2 (training time)."""
    input:
        reports=lambda wc: [f"{RESULTS}/{s}/report.html" for s in SCENES],
        metrics=lambda wc: [f"{RESULTS}/{s}/metrics.json" for s in SCENES],
    output:
        f"{RESULTS}/batch_{{batch}}.html",
    params:
        py=PY,
        folders=lambda wc: " ".join(f"{RESULTS}/{s}" for s in SCENES),
        scenes=lambda wc: ",".join(SCENES),
    log:
        f"{RESULTS}/logs/batch_{{batch}}.log",
    shell:
        "{params.py} -m stages.report batch {params.folders} --title 'batch {wildcards.batch}: {params.scenes}' "
        "--out {output} > {log} 2>&1"
