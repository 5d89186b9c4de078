rule init:
    """Dense Gaussian initialisation from the capture's depth + diffuse buffers."""
    input:
        capture=training_capture,
    output:
        f"{RESULTS}/{{scene}}/init/points.ply",
    params:
        py=PY,
        cfg=section("init"),
    log:
        f"{RESULTS}/{{scene}}/logs/init.log",
    shell:
        "{params.py} -m stages.progress --label 'init {wildcards}' --log {log} -- "
        "{params.py} -m stages.init --config-json {params.cfg:q} --capture {input.capture} --out $(dirname {output})"
