rule poses:
    """Photos -> COLMAP poses (pycolmap SfM, or the model already beside the photos) -> a normalised capture
    with SfM points. Only for scenes of kind photos; synthetic scenes get their capture from synth."""
    input:
        photos=photos_input,
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


rule synth_photos:
    """A photos scene whose truth is known (photos_of): its synth section rendered, train views only, as 8-bit
    sRGB PNG photos (no buffers, no poses: what rule poses starts from) beside the capture they came from (true
    cameras and exact buffers, for scoring)."""
    output:
        photos=directory(f"{RESULTS}/{{scene}}/photos"),
        capture=directory(f"{RESULTS}/{{scene}}/photos_capture"),
    wildcard_constraints:
        scene=scenes_with_photos_of(),
    params:
        py=PY,
        cfg=section("synth"),
    log:
        f"{RESULTS}/{{scene}}/logs/synth_photos.log",
    shell:
        "{params.py} -m stages.progress --label 'synth_photos {wildcards}' --log {log} -- "
        "{params.py} -m stages.synth --config-json {params.cfg:q} --splits train --threads {threads} "
        "--out {output.capture} --photos {output.photos}"


rule photos_truth:
    """The test views of the photos_of truth scene (exact buffers) moved into the posed frame by the similarity of
    the true and posed train cameras, with the pose errors and the network's buffer errors (what limits the run)
    in its capture.yaml (photos_path); render and evaluate score the photos run on it."""
    input:
        truth=lambda wc: f"{RESULTS}/{photos_of(wc.scene)['truth']}/capture",
        reference=f"{RESULTS}/{{scene}}/photos_capture",
        posed=f"{RESULTS}/{{scene}}/capture",
        predicted=training_capture,
    output:
        directory(f"{RESULTS}/{{scene}}/capture_eval"),
    wildcard_constraints:
        scene=scenes_with_photos_of(),
    params:
        py=PY,
        truth=lambda wc: photos_of(wc.scene)["truth"],
    log:
        f"{RESULTS}/{{scene}}/logs/photos_truth.log",
    shell:
        "{params.py} -m stages.progress --label 'photos_truth {wildcards}' --log {log} -- "
        "{params.py} -m stages.poses align --truth {input.truth} --reference {input.reference} "
        "--posed {input.posed} --predicted {input.predicted} --truth-scene {params.truth} --out {output}"
