rule poses:
    """Photos -> COLMAP poses (pycolmap SfM, or the model already beside the photos) -> a normalised capture
    with SfM points. Only for scenes of kind photos; synthetic scenes get their capture from synth."""
    input:
        photos=lambda wc: scene_config(wc.scene)["poses"]["images"],
    output:
        capture=directory(f"{RESULTS}/{{scene}}/capture"),
        work=directory(f"{RESULTS}/{{scene}}/poses"),
    wildcard_constraints:
        scene=scenes_of_kind("photos"),
    params:
        py=PY,
        cfg=section("poses"),
    log:
        f"{RESULTS}/{{scene}}/logs/poses.log",
    shell:
        "{params.py} -m stages.progress --label 'poses {wildcards}' --log {log} -- "
        "{params.py} -m stages.poses --config-json {params.cfg:q} --images {input.photos:q} --work {output.work} "
        "--out {output.capture} --threads {threads}"
