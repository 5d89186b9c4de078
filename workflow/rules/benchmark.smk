rule benchmark_tracer:
    """Tracer speed table (stdout, log) and JSON: forward, fused backward, traversal, BVH, threads."""
    output:
        f"{RESULTS}/benchmark/tracer.json",
    log:
        f"{RESULTS}/benchmark/tracer.log",
    threads: 2
    shell:
        "{PY} -m stages.benchmark tracer --out {output} 2>&1 | tee {log}"
