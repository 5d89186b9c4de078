# Named edits of a scene (config edits:, models/editing/spec.py): edited model + renders of the test views, and
# for synthetic scenes the ground truth re-rendered (synth stage) with the edit's synth counterpart, scored next
# to the unedited renders. Target: snakemake --cores 2 edits --config scene=demo


# the scene wildcard of render / reconstruct / evaluate would also match results/<scene>/edits/<name>/...
ruleorder: edit > render
ruleorder: edit > reconstruct
ruleorder: edit_metrics > evaluate


rule edits:
    """Every named edit of the requested scenes (not part of `all`: each costs a render, plus a Mitsuba
    ground truth for synthetic scenes)."""
    input:
        # per scene and edit: metrics.json where a ground truth can be rendered, else the edited renders
        lambda wc: [t for scene in SCENES for t in edit_targets(scene)],


rule edit:
    """Apply one named edit to the trained model and render the capture's test views (N spp + denoiser)."""
    input:
        capture=f"{RESULTS}/{{scene}}/capture",
        model=f"{RESULTS}/{{scene}}/model/model.yaml",
    output:
        model=f"{RESULTS}/{{scene}}/edits/{{edit}}/model/model.yaml",
        renders=directory(f"{RESULTS}/{{scene}}/edits/{{edit}}/renders"),
    wildcard_constraints:
        scene="[A-Za-z0-9_-]+",
        edit="[A-Za-z0-9_-]+",
    params:
        py=PY,
        edit=lambda wc: json.dumps(scene_edit(wc.scene, wc.edit), sort_keys=True),
        cfg=section("render"),
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/{{scene}}/logs/edit_{{edit}}.log",
    resources:
        gpu=scene_gpus,
    shell:
        "{params.py} -m stages.progress --label 'edit {wildcards}' --log {log} -- "
        "{params.py} -m stages.edit apply --edit {wildcards.edit} --edit-json {params.edit:q} "
        "--config-json {params.cfg:q} --model $(dirname {input.model}) --capture {input.capture} "
        "--out $(dirname {output.renders}) --device {params.device} --threads {threads}"


rule edit_truth:
    """Ground truth of one edit: the synthetic scene's test views rendered by the synth stage with the edit's
    ground_truth ops (each view with the sampler seed it has in the capture)."""
    output:
        directory(f"{RESULTS}/{{scene}}/edits/{{edit}}/truth"),
    wildcard_constraints:
        scene="[A-Za-z0-9_-]+",
        edit="[A-Za-z0-9_-]+",
    params:
        py=PY,
        ground_truth=lambda wc: json.dumps(scene_edit(wc.scene, wc.edit).get("ground_truth") or [],
                                           sort_keys=True),
        synth=section("synth"),
    log:
        f"{RESULTS}/{{scene}}/logs/edit_truth_{{edit}}.log",
    shell:
        "{params.py} -m stages.progress --label 'edit_truth {wildcards}' --log {log} -- "
        "{params.py} -m stages.synth --config-json {params.synth:q} --edits-json {params.ground_truth:q} "
        "--splits test --name edit:{wildcards.edit} --no-progress --threads {threads} --out {output}"


rule edit_metrics:
    """PSNR / SSIM per layer of the edited renders vs the edited ground truth, next to the unedited renders vs
    the capture, and both on the pixels the edit changed."""
    input:
        capture=f"{RESULTS}/{{scene}}/capture",
        truth=edit_truth,
        renders=f"{RESULTS}/{{scene}}/edits/{{edit}}/renders",
        baseline=f"{RESULTS}/{{scene}}/renders",
    output:
        f"{RESULTS}/{{scene}}/edits/{{edit}}/metrics.json",
    wildcard_constraints:
        scene="[A-Za-z0-9_-]+",
        edit="[A-Za-z0-9_-]+",
    params:
        py=PY,
    log:
        f"{RESULTS}/{{scene}}/logs/edit_metrics_{{edit}}.log",
    shell:
        "{params.py} -m stages.progress --label 'edit_metrics {wildcards}' --log {log} -- "
        "{params.py} -m stages.edit evaluate --edit {wildcards.edit} --capture {input.capture} "
        "--truth {input.truth} --renders {input.renders}/test --baseline-renders {input.baseline}/test "
        "--out {output}"
