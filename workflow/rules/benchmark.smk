rule benchmark_tracer:
    """Tracer speed table (stdout, log) and JSON: forward, fused backward, traversal, BVH, threads."""
    output:
        f"{RESULTS}/benchmark/tracer.json",
    params:
        py=PY,
    log:
        f"{RESULTS}/benchmark/tracer.log",
    threads: 2
    shell:
        "{params.py} -m stages.benchmark tracer --out {output} 2>&1 | tee {log}"
