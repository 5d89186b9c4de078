"""Training-step benchmark: milliseconds per ``Trainer.train_step`` split into sections, at several ray counts.

The step is the real one (models.reconstruction.Trainer on a models.tracer.Tracer) on a synthetic capture built in
memory (room_capture.py), with reflections on from the first step (max path length 3), no far field and no pruning,
so every timed step does the same work. Each row: ``steps`` steps timed whole with no profiling (``step_ms``, the
honest figure), then ``steps`` more with a ``SectionTimer`` (device synchronised at section boundaries) giving

    tracer_forward / tracer_backward   the tracer's kernel launches (forward, backward + chain rule)
    bvh_update                         per-step preparation kernel + BVH refit
    path_sampling                      the bounce loop's torch math (sampling, throughput, scatter), tracer excluded
    losses                             loss terms and metrics
    autograd                           torch's backward pass, the tracer's backward excluded
    optimizer                          Adam step + clamps
    host_ms                            the rest: the tracer's host side (array conversions, allocations, read-backs,
                                       ``tracer_host_ms``) plus whatever the step spends outside every section

``step_cpu_ms``: CPU seconds of the process per step (all threads; steadier than wall time on a shared machine).
Medians over the steps. The "overhead floor" is the step at 64 rays, where kernel work is ~0: what a step costs
whatever the GPU.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch

from models.profiling import NO_TIMER, SectionTimer, device_sync
from models.reconstruction import ReconstructConfig, Trainer
from models.tracer import Tracer, TracerConfig
from stages.benchmark.room_capture import room_capture
from stages.provenance import peak_memory

WORK = ("tracer_forward", "tracer_backward", "bvh_update", "path_sampling", "losses", "autograd", "optimizer")
LARGE_VIEW = (768, 576)


@dataclass
class TrainStepBenchmarkConfig:
    rays: list[int] = field(default_factory=lambda: [64, 1024, 4096])  # random rays per step (one row each)
    views: list[tuple[int, int]] = field(default_factory=lambda: [(128, 96)])  # whole views per step (W, H)
    large_view: bool | None = None  # add a 768x576 whole view; None: on CUDA only (a CPU step takes seconds)
    n_gaussians: int = 50_000  # Gaussians of the room (and of the initialisation that is trained)
    n_views: int = 4           # training views of the synthetic capture
    steps: int = 5             # timed steps per row (and as many profiled ones)
    warmup_steps: int = 2      # untimed steps first (kernel compilation, replay capacity)
    max_path_length: int = 3
    devices: list[str] = field(default_factory=lambda: ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    threads: int = 2           # tracer CPU threads
    torch_threads: int = 1
    seed: int = 0
    sync_checks: bool = False  # the tracer's checks read back at every trace (the trainer defers them on a GPU)
    # a real run instead of the random room (bench_checkpoint): its checkpoint, scene, capture and init
    checkpoint: str | None = None
    scene: str | None = None
    capture: str | None = None
    init: str | None = None

    def __post_init__(self) -> None:
        given = {k: getattr(self, k) for k in ("checkpoint", "scene", "capture", "init")}
        if any(v is not None for v in given.values()) and any(v is None for v in given.values()):
            missing = ", ".join(f"--{k}" for k, v in given.items() if v is None)
            raise ValueError(f"a checkpoint row needs --checkpoint, --scene, --capture and --init together; "
                             f"missing {missing}")
        if self.checkpoint is not None and not Path(self.checkpoint).is_file():
            raise ValueError(f"checkpoint {self.checkpoint} not found (a reconstruct run writes "
                             "<model>/checkpoints/last.pt)")
        if any(n < 1 for n in self.rays):
            raise ValueError(f"rays must be positive, got {self.rays}")
        for w, h in self.views:
            if w < 1 or h < 1:
                raise ValueError(f"view sizes must be positive, got {w}x{h}")
        for name in ("n_gaussians", "n_views", "steps", "max_path_length", "threads", "torch_threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.warmup_steps < 0:
            raise ValueError(f"warmup_steps must be >= 0, got {self.warmup_steps}")
        unknown = [d for d in self.devices if d != "cpu" and not d.startswith("cuda")]
        if unknown:
            raise ValueError(f"devices must be cpu or cuda[:i], got {unknown}")

    @staticmethod
    def quick() -> "TrainStepBenchmarkConfig":
        return TrainStepBenchmarkConfig(rays=[64, 256], views=[(32, 24)], large_view=False, n_gaussians=2000,
                                        n_views=2, steps=2, warmup_steps=1, devices=["cpu"])


def _trainer(capture, init, rays_per_step: int, tracer: Tracer, cfg: TrainStepBenchmarkConfig) -> Trainer:
    recon = ReconstructConfig(iterations=10**9, warmup=0, rays_per_step=rays_per_step, far_field="off",
                              plane_fill_count=0, prune_every=0, max_path_length=cfg.max_path_length,
                              checkpoint_every=10**9, seed=cfg.seed)
    return Trainer(capture, init, recon, tracer)


def bench_row(capture, init, rays_per_step: int, device: str, cfg: TrainStepBenchmarkConfig) -> dict:
    """One row: ``rays_per_step`` random rays (0 = a whole view) per step on ``device``."""
    tracer = Tracer(TracerConfig(num_threads=cfg.threads), device)
    trainer = _trainer(capture, init, rays_per_step, tracer, cfg)
    cam = capture.views[0].camera
    return _measure(trainer, tracer, cfg, rays_per_step or cam.width * cam.height,
                    f"{cam.width}x{cam.height}" if rays_per_step == 0 else None)


def bench_checkpoint(reconstruct: dict, capture, init, checkpoint: Path, device: str,
                     cfg: TrainStepBenchmarkConfig, progress=print) -> dict:
    """One row: a scene's own Trainer (its merged ``reconstruct`` section, the tracer threads of ``cfg``) resumed from
    a run's ``checkpoint``: the steps that run takes at that point (its Gaussians, fills, path length, rays), not a
    random room's. A checkpoint written under another config still loads (its parameters and state are what is
    timed); the difference is reported."""
    config = ReconstructConfig.from_dict(reconstruct)
    config = replace(config, tracer=replace(config.tracer, num_threads=cfg.threads))
    tracer = Tracer(config.tracer, device)
    trainer = Trainer(capture, init, config, tracer)
    state = trainer.read_checkpoint(checkpoint)
    # the inputs are the caller's to match (the stage records their digests): only the config is compared here
    trainer.inputs = dict((state.get("fingerprint") or {}).get("inputs", {}))
    why = trainer.resume_mismatch(state)
    trainer.load_state_dict(state)
    step = trainer.step
    row = _measure(trainer, tracer, cfg, config.rays_per_step, None)
    row.update(checkpoint=str(checkpoint), step=step,
               checkpoint_config=None if why is None else why)
    if why is not None:
        progress(f"train-step benchmark: note: {checkpoint} {why}")
    return row


def _checkpoint_row(cfg: TrainStepBenchmarkConfig, device: str, progress) -> dict:
    from models.capture import read_capture
    from models.gaussians import read_ply
    from stages.config import load_config

    progress(f"train-step benchmark: {device}: {cfg.scene} resumed from {cfg.checkpoint} ...")
    reconstruct = load_config(cfg.scene).get("reconstruct", {})
    return bench_checkpoint(reconstruct, read_capture(Path(cfg.capture)), read_ply(Path(cfg.init)),
                            Path(cfg.checkpoint), device, cfg, progress)


def _measure(trainer: Trainer, tracer: Tracer, cfg: TrainStepBenchmarkConfig, rays: int, whole_view) -> dict:
    """``cfg.warmup_steps`` untimed steps, ``cfg.steps`` timed whole, ``cfg.steps`` more with section timers."""
    trainer.defer_checks = trainer.defer_checks and not cfg.sync_checks
    sync = device_sync(tracer.device)
    for _ in range(cfg.warmup_steps):
        trainer.train_step()
    plain, cpu = [], []
    for _ in range(cfg.steps):
        sync()
        start, cpu_start = time.perf_counter(), time.process_time()
        trainer.train_step()
        sync()
        plain.append((time.perf_counter() - start) * 1e3)
        cpu.append((time.process_time() - cpu_start) * 1e3)
    timer = SectionTimer(sync)
    trainer.timer = tracer.timer = timer
    profiled = []
    for _ in range(cfg.steps):
        sync()
        start = time.perf_counter()
        trainer.train_step()
        sync()
        sections = timer.take()
        sections["total"] = (time.perf_counter() - start) * 1e3
        profiled.append(sections)
    trainer.timer = tracer.timer = NO_TIMER
    busy = gpu_busy(trainer.train_step, sync) if tracer.device.startswith("cuda") else None
    tracer.close()
    median = lambda key: statistics.median(p.get(key, 0.0) for p in profiled)  # noqa: E731
    row = {"device": tracer.device, "rays": rays, "whole_view": whole_view,
           "n_gaussians": len(trainer.params["means"]), "deferred_checks": trainer.defer_checks,
           "step_ms": statistics.median(plain),
           "step_ms_min": min(plain), "step_cpu_ms": statistics.median(cpu), "profiled_step_ms": median("total")}
    for key in WORK:
        row[f"{key}_ms"] = median(key)
    row["gpu_busy"] = busy
    row["tracer_host_ms"] = median("tracer_host")
    row["host_ms"] = statistics.median(p["total"] - sum(p.get(k, 0.0) for k in WORK) for p in profiled)
    row["other_host_ms"] = row["host_ms"] - row["tracer_host_ms"]
    return row


def gpu_busy(step, sync, seconds: float = 3.0, interval: float = 0.05) -> float | None:
    """Fraction of time the GPU runs a kernel while ``step`` repeats for ``seconds``: NVML's utilisation (what
    nvidia-smi shows), sampled every ``interval`` s in a thread, median of the samples; None without NVML."""
    import threading

    try:
        torch.cuda.utilization()
    except Exception:  # noqa: BLE001 - NVML (pynvml) missing or not permitted: no figure, not an error
        return None
    samples, stop = [], threading.Event()

    def sample():
        while not stop.wait(interval):
            samples.append(torch.cuda.utilization())

    thread = threading.Thread(target=sample, daemon=True)
    step()
    sync()
    start = time.perf_counter()
    thread.start()
    try:
        while time.perf_counter() - start < seconds:
            step()
        sync()
    finally:
        stop.set()
        thread.join()
    # the first samples may still cover the time before the loop (NVML averages over its own sample period)
    return statistics.median(samples[len(samples) // 4:]) / 100.0 if samples else None


def run_train_step_benchmark(cfg: TrainStepBenchmarkConfig, progress=print) -> dict:
    start = time.perf_counter()
    saved_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.torch_threads)
    rows, memory = [], {}
    try:
        for device in cfg.devices:
            if device.startswith("cuda"):
                torch.cuda.reset_peak_memory_stats()
            if cfg.checkpoint is not None:
                rows.append(_checkpoint_row(cfg, device, progress))
                memory[device] = peak_memory(device)
                continue
            renderer = Tracer(TracerConfig(num_threads=cfg.threads), device)
            views = list(cfg.views)
            large = cfg.large_view if cfg.large_view is not None else device.startswith("cuda")
            if large and LARGE_VIEW not in views:
                views.append(LARGE_VIEW)
            w, h = views[0] if views else (128, 96)
            progress(f"train-step benchmark: {device}: capture {cfg.n_views} views {w}x{h}, "
                     f"{cfg.n_gaussians} Gaussians ...")
            capture, init = room_capture(renderer, cfg.n_gaussians, cfg.n_views, w, h, cfg.seed)
            for n in cfg.rays:
                progress(f"train-step benchmark: {device}: {n} rays per step ...")
                rows.append(bench_row(capture, init, n, device, cfg))
            for i, (w, h) in enumerate(views):
                if i > 0:
                    progress(f"train-step benchmark: {device}: capture {cfg.n_views} views {w}x{h} ...")
                    capture, init = room_capture(renderer, cfg.n_gaussians, cfg.n_views, w, h, cfg.seed)
                progress(f"train-step benchmark: {device}: whole {w}x{h} view per step ...")
                rows.append(bench_row(capture, init, 0, device, cfg))
            renderer.close()
            memory[device] = peak_memory(device)  # on CUDA: torch's and Warp's peaks (stages/provenance.py)
    finally:
        torch.set_num_threads(saved_threads)
    import warp as wp

    floors = {r["device"]: r for r in rows if r["whole_view"] is None and r["rays"] == min(cfg.rays)}
    return {
        "benchmark": "train-step",
        "config": asdict(cfg),
        "sections": {"work": list(WORK), "host": "host_ms = profiled step - work sections (tracer_host_ms + "
                     "other_host_ms)"},
        "results": rows,
        "overhead_floor": {d: {"rays": r["rays"], "step_ms": r["step_ms"], "host_ms": r["host_ms"]}
                           for d, r in floors.items()},
        "memory": memory,
        "provenance": {
            "torch": torch.__version__, "warp": wp.__version__, "python": platform.python_version(),
            "cpu_count": os.cpu_count(), "load_average": list(os.getloadavg()), "wall_s": time.perf_counter() - start,
            "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
        },
    }


COLUMNS = [
    ("device", "device", "{}"), ("rays", "rays", "{:d}"), ("view", "whole_view", "{}"),
    ("step ms", "step_ms", "{:.1f}"), ("cpu ms", "step_cpu_ms", "{:.1f}"),
    ("profiled", "profiled_step_ms", "{:.1f}"), ("trace fwd", "tracer_forward_ms", "{:.1f}"),
    ("trace bwd", "tracer_backward_ms", "{:.1f}"), ("bvh", "bvh_update_ms", "{:.1f}"),
    ("paths", "path_sampling_ms", "{:.1f}"), ("losses", "losses_ms", "{:.1f}"), ("autograd", "autograd_ms", "{:.1f}"),
    ("adam", "optimizer_ms", "{:.1f}"), ("host", "host_ms", "{:.1f}"), ("(tracer host", "tracer_host_ms", "{:.1f}"),
    ("other host)", "other_host_ms", "{:.1f}"), ("GPU busy", "gpu_busy", "{:.0%}"),
]


def format_table(result: dict) -> str:
    head = [c[0] for c in COLUMNS]
    body = [[fmt.format(r[key]) if r.get(key) is not None else "-" for _, key, fmt in COLUMNS]
            for r in result["results"]]
    widths = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(head)]
    line = lambda cells: "  ".join(c.rjust(w) for c, w in zip(cells, widths))  # noqa: E731
    c = result["config"]
    what = (f"{c['scene']} resumed from {c['checkpoint']} at step {result['results'][0]['step']}, "
            f"{result['results'][0]['n_gaussians']} Gaussians" if c.get("checkpoint") else
            f"{c['n_gaussians']} Gaussians, max path length {c['max_path_length']}")
    lines = [f"ms per training step ({what}; medians of {c['steps']} steps; profiled = with section timers and "
             "device syncs)", line(head), line(["-" * w for w in widths]), *map(line, body)]
    for device, f in result["overhead_floor"].items():
        lines.append(f"overhead floor ({device}, {f['rays']} rays): {f['step_ms']:.1f} ms per step, "
                     f"host {f['host_ms']:.1f} ms")
    return "\n".join(lines)
