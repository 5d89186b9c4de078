# The buffer network: training data (procedural rooms), training, held-out evaluation, and the buffers stage
# that fills a scene's capture with its predictions. Target: snakemake --cores 2 buffernet


rule buffernet_rooms:
    """Random synthetic rooms (Mitsuba, exact buffers) for training / held-out evaluation."""
    output:
        directory(f"{RESULTS}/buffernet/rooms_{{split}}"),
    wildcard_constraints:
        split="train|heldout",
    params:
        py=PY,
        r=lambda wc: buffernet_section("rooms")[wc.split],
        common=lambda wc: buffernet_section("rooms"),
        denoise=lambda wc: "" if buffernet_section("rooms").get("denoise", True) else "--no-denoise",
    log:
        f"{RESULTS}/buffernet/logs/rooms_{{split}}.log",
    shell:
        "{params.py} -m stages.progress --label 'buffernet_rooms {wildcards}' --log {log} -- "
        "{params.py} -m stages.synth procedural --count {params.r[count]} --seed {params.r[seed]} --out {output} "
        "--resolution {params.common[resolution][0]} {params.common[resolution][1]} --views {params.common[views]} "
        "--spp {params.common[spp]} {params.denoise} --no-progress"


rule buffernet_train:
    """Train a buffer network (buffernet.train; name = the folder under results/buffernet/)."""
    input:
        rooms=f"{RESULTS}/buffernet/rooms_train",
    output:
        directory(f"{RESULTS}/buffernet/{{name}}/pipeline"),
    params:
        py=PY,
        args=lambda wc: " ".join(
            (f"--{k.replace('_', '-')}" if v else f"--no-{k.replace('_', '-')}") if isinstance(v, bool)
            else f"--{k.replace('_', '-')} {v}" for k, v in buffernet_section("train").items()),
    log:
        f"{RESULTS}/buffernet/logs/train_{{name}}.log",
    shell:
        "{params.py} -m stages.progress --label 'buffernet_train {wildcards}' --log {log} -- "
        "{params.py} -m stages.buffernet_train train --data captures:{input.rooms} --out $(dirname {output}) "
        "{params.args} --no-progress"


rule buffernet_evaluate:
    """Per-buffer accuracy on held-out rooms vs trivial baselines (table in the log, JSON)."""
    input:
        model=f"{RESULTS}/buffernet/{{name}}/pipeline",
        rooms=f"{RESULTS}/buffernet/rooms_heldout",
    output:
        f"{RESULTS}/buffernet/{{name}}/heldout.json",
    params:
        py=PY,
    log:
        f"{RESULTS}/buffernet/logs/evaluate_{{name}}.log",
    shell:
        "{params.py} -m stages.progress --label 'buffernet_evaluate {wildcards}' --log {log} -- "
        "{params.py} -m stages.buffernet_train evaluate --model {input.model} --data captures:{input.rooms} "
        "--out {output} --no-progress"


rule buffernet:
    """Train and evaluate the workflow's buffer network: snakemake --cores 2 buffernet"""
    input:
        f"{RESULTS}/buffernet/{buffernet_section('name')}/heldout.json",


rule buffers:
    """A scene's capture with network-predicted buffers (buffers.predict), for init and reconstruct."""
    input:
        capture=f"{RESULTS}/{{scene}}/capture",
        model=lambda wc: buffernet_model(wc.scene),
    output:
        directory(f"{RESULTS}/{{scene}}/capture_net"),
    params:
        py=PY,
        cfg=section("buffers"),
        device=lambda wc: scene_config(wc.scene)["device"],
    log:
        f"{RESULTS}/{{scene}}/logs/buffers.log",
    resources:
        gpu=scene_gpus,
    shell:
        "{params.py} -m stages.progress --label 'buffers {wildcards}' --log {log} -- "
        "{params.py} -m stages.buffers --config-json {params.cfg:q} --capture {input.capture} --model {input.model} "
        "--out {output} --device {params.device} --no-progress"
