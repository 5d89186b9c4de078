rule reconstruct:
    """Optimise the Gaussian scene (warm-up, then path-traced reflections) into the model folder: gaussians.ply +
    model.yaml (the tracer / path settings every consumer renders it with). An interrupted run resumes from
    model/checkpoints/last.pt when that checkpoint was written under the same config and inputs (otherwise it is
    kept aside and training starts afresh)."""
    input:
        capture=training_capture,
        init=f"{RESULTS}/{{scene}}/init/points.ply",
    output:
        gaussians=f"{RESULTS}/{{scene}}/model/gaussians.ply",
        settings=f"{RESULTS}/{{scene}}/model/model.yaml",
    params:
        py=PY,
        cfg=section("reconstruct"),
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/{{scene}}/logs/reconstruct.log",
    resources:
        gpu=scene_gpus,
    shell:
        "{params.py} -m stages.progress --label 'reconstruct {wildcards}' --log {log} -- "
        "{params.py} -m stages.reconstruct --config-json {params.cfg:q} --capture {input.capture} "
        "--init {input.init} --out $(dirname {output.gaussians}) --device {params.device} --threads {threads} --resume"


rule render:
    """N spp renders + denoiser of the test views and a novel camera path, every layer as EXR + PNG."""
    input:
        capture=eval_capture,
        model=f"{RESULTS}/{{scene}}/model/model.yaml",
    output:
        # the key pictures of the renders (final / diffuse / specular of each test view) go into `snakemake --report`
        report(directory(f"{RESULTS}/{{scene}}/renders"), caption="../report/renders.rst", category="Renders",
               subcategory="{scene}",
               patterns=["test/png/{view}_final.png", "test/png/{view}_diffuse.png", "test/png/{view}_specular.png"]),
    params:
        py=PY,
        cfg=section("render"),
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/{{scene}}/logs/render.log",
    resources:
        gpu=scene_gpus,
    shell:
        "{params.py} -m stages.progress --label 'render {wildcards}' --log {log} -- "
        "{params.py} -m stages.render --config-json {params.cfg:q} --capture {input.capture} "
        "--model $(dirname {input.model}) --out {output} --device {params.device} --threads {threads}"


rule evaluate:
    """PSNR / SSIM per layer on the test split (linear and tonemapped), LPIPS with evaluate.lpips, training time,
    Gaussian count, peak memory, render FPS at 1 spp."""
    input:
        capture=eval_capture,
        renders=f"{RESULTS}/{{scene}}/renders",
        model=f"{RESULTS}/{{scene}}/model/model.yaml",
        # evaluate.lpips: the local weight files (backbone, lin), when set
        lpips=lambda wc: sorted((scene_config(wc.scene).get("evaluate", {}).get("lpips") or {}).values()),
    output:
        report(f"{RESULTS}/{{scene}}/metrics.json", caption="../report/metrics.rst", category="Scene reports",
               labels={"scene": "{scene}", "file": "metrics.json"}),
    params:
        py=PY,
        cfg=section("evaluate"),
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/{{scene}}/logs/evaluate.log",
    resources:
        gpu=scene_gpus,
    shell:
        "{params.py} -m stages.progress --label 'evaluate {wildcards}' --log {log} -- "
        "{params.py} -m stages.evaluate --capture {input.capture} --renders {input.renders} "
        "--model $(dirname {input.model}) --config-json {params.cfg:q} --device {params.device} "
        "--threads {threads} --out {output}"
