rule benchmark_tracer:
    """Tracer speed tables (stdout, log) and JSON: forward, fused backward, traversal, BVH, threads; scene types vs Mitsuba 3."""
    output:
        f"{RESULTS}/benchmark/tracer.json",
    params:
        py=PY,
    log:
        f"{RESULTS}/benchmark/tracer.log",
    threads: 2
    shell:
        "{params.py} -m stages.benchmark tracer --out {output} 2>&1 | tee {log}"


rule benchmark_train_step:
    """Training-step table (stdout, log) and JSON: ms per step by section (tracer kernels, path sampling, losses,
    Adam, host overhead) at 64 / 1024 / 4096 rays and whole views; on the CPU, and on CUDA when present."""
    output:
        f"{RESULTS}/benchmark/train_step.json",
    params:
        py=PY,
    log:
        f"{RESULTS}/benchmark/train_step.log",
    threads: 2
    shell:
        "{params.py} -m stages.benchmark train-step --out {output} 2>&1 | tee {log}"


rule sweep:
    """Speed/accuracy sweep of one scene: table (log) and sweep.json (target: sweep_all)."""
    input:
        capture=f"{RESULTS}/{{scene}}/capture",
    output:
        json=f"{RESULTS}/sweep/{{scene}}/sweep.json",
    params:
        py=PY,
        cfg=lambda wc: json.dumps(scene_config(wc.scene), sort_keys=True),
        iterations=lambda wc: scene_config(wc.scene)["sweep"]["iterations"],
        quick=lambda wc: "--quick" if scene_config(wc.scene)["sweep"]["quick"] else "",
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/sweep/{{scene}}/sweep.log",
    resources:
        gpu=scene_gpus,
    shell:
        "{params.py} -m stages.progress --label 'sweep {wildcards}' --log {log} -- "
        "{params.py} -m stages.benchmark sweep --capture {input.capture} --scene {wildcards.scene} "
        "--config-json {params.cfg:q} --iterations {params.iterations} {params.quick} --device {params.device} "
        "--out $(dirname {output.json})"


rule sweep_report:
    """The sweep drawn by the report stage: Pareto plots, table, recommended settings."""
    input:
        f"{RESULTS}/sweep/{{scene}}/sweep.json",
    output:
        f"{RESULTS}/sweep/{{scene}}/report.html",
    params:
        py=PY,
    log:
        f"{RESULTS}/sweep/{{scene}}/report.log",
    shell:
        "{params.py} -m stages.progress --label 'sweep_report {wildcards}' --log {log} -- "
        "{params.py} -m stages.report sweep {input} --out {output}"


rule sweep_all:
    """The sweep of every requested scene: snakemake --cores 2 sweep_all --config scene=demo"""
    input:
        [f"{RESULTS}/sweep/{s}/report.html" for s in SCENES],
