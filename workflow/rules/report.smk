rule report:
    """Self-contained HTML report of one scene: ground truth vs ours per layer, error maps, training curves,
    metrics, cost, what the scene required and what was switched off, edits."""
    input:
        unpack(report_inputs),
    output:
        report(f"{RESULTS}/{{scene}}/report.html", caption="../report/scene_report.rst", category="Scene reports",
               labels={"scene": "{scene}", "file": "report.html"}),
    params:
        py=PY,
        cfg=lambda wc: json.dumps(scene_config(wc.scene), sort_keys=True),
        folder=lambda wc: f"{RESULTS}/{wc.scene}",
    log:
        f"{RESULTS}/{{scene}}/logs/report.log",
    shell:
        "{params.py} -m stages.progress --label 'report {wildcards}' --log {log} -- "
        "{params.py} -m stages.report scene {params.folder} --config-json {params.cfg:q} --out {output} "
        "--command \"$ER_WORKFLOW_COMMAND\""


rule batch_report:
    """Scenes side by side like the paper's Tables 1 (PSNR diffuse / specular / final) and 2 (training time)."""
    input:
        reports=lambda wc: [f"{RESULTS}/{s}/report.html" for s in SCENES],
        metrics=lambda wc: [f"{RESULTS}/{s}/metrics.json" for s in SCENES],
    output:
        report(f"{RESULTS}/batch_{{batch}}.html", caption="../report/batch_report.rst", category="Batch reports",
               labels={"batch": "{batch}"}),
    params:
        py=PY,
        folders=lambda wc: " ".join(f"{RESULTS}/{s}" for s in SCENES),
        scenes=lambda wc: ",".join(SCENES),
        presets=lambda wc: json.dumps({s: scene_config(s)["presets"] for s in SCENES}, sort_keys=True),
    log:
        f"{RESULTS}/logs/batch_{{batch}}.log",
    shell:
        "{params.py} -m stages.progress --label 'batch_report {wildcards}' --log {log} -- "
        "{params.py} -m stages.report batch {params.folders} --title 'batch {wildcards.batch}: {params.scenes}' "
        "--presets-json {params.presets:q} --command \"$ER_WORKFLOW_COMMAND\" --out {output}"
