rule synth:
    """Render a synthetic scene with exact buffers into a capture (Mitsuba 3)."""
    output:
        directory(f"{RESULTS}/{{scene}}/capture"),
    wildcard_constraints:
        scene=scenes_of_kind("synthetic"),  # photos scenes get their capture from rule poses
    params:
        py=PY,
        cfg=section("synth"),
    log:
        f"{RESULTS}/{{scene}}/logs/synth.log",
    shell:
        "{params.py} -m stages.progress --label 'synth {wildcards}' --log {log} -- "
        "{params.py} -m stages.synth --config-json {params.cfg:q} --threads {threads} --out {output}"
