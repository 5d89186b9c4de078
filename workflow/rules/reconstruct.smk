rule reconstruct:
    """Optimise the Gaussian scene (warm-up, then path-traced reflections) into the model folder: gaussians.ply +
    model.yaml (the tracer / path settings every consumer renders it with)."""
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
    threads: 2
    shell:
        "{params.py} -m stages.reconstruct --config-json {params.cfg:q} --capture {input.capture} "
        "--init {input.init} --out $(dirname {output.gaussians}) --device {params.device} > {log} 2>&1"


rule render:
    """N spp renders + denoiser of the test views and a novel camera path, every layer as EXR + PNG."""
    input:
        capture=f"{RESULTS}/{{scene}}/capture",
        model=f"{RESULTS}/{{scene}}/model/model.yaml",
    output:
        directory(f"{RESULTS}/{{scene}}/renders"),
    params:
        py=PY,
        cfg=section("render"),
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/{{scene}}/logs/render.log",
    threads: 2
    shell:
        "{params.py} -m stages.render --config-json {params.cfg:q} --capture {input.capture} "
        "--model $(dirname {input.model}) --out {output} --device {params.device} > {log} 2>&1"


rule evaluate:
    """PSNR / SSIM per layer on the test split (linear and tonemapped), training time, Gaussian count, peak memory,
    render FPS at 1 spp."""
    input:
        capture=f"{RESULTS}/{{scene}}/capture",
        renders=f"{RESULTS}/{{scene}}/renders",
        model=f"{RESULTS}/{{scene}}/model/model.yaml",
    output:
        f"{RESULTS}/{{scene}}/metrics.json",
    params:
        py=PY,
        cfg=section("evaluate"),
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/{{scene}}/logs/evaluate.log",
    threads: 2
    shell:
        "{params.py} -m stages.evaluate --capture {input.capture} --renders {input.renders} "
        "--model $(dirname {input.model}) --config-json {params.cfg:q} --device {params.device} "
        "--threads {threads} --out {output} > {log} 2>&1"
