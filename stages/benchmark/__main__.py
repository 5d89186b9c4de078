"""CLI: python -m stages.benchmark tracer [--sizes 50000,200000] [--res 128,256] [--threads 1,2]
[--repeats 3] [--device cpu] [--torch-threads 1] [--out FILE.json] [--quick]"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

from stages.benchmark.tracer import TracerBenchmarkConfig, format_table, run_tracer_benchmark


def _ints(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def parse_args(argv=None) -> tuple[str, TracerBenchmarkConfig, Path | None]:
    p = argparse.ArgumentParser(prog="python -m stages.benchmark", description=__doc__)
    p.add_argument("what", choices=["tracer"], help="which benchmark")
    p.add_argument("--sizes", type=_ints, help="numbers of Gaussians, e.g. 50000,200000")
    p.add_argument("--res", type=_ints, help="square resolutions, e.g. 128,256")
    p.add_argument("--threads", type=_ints, help="CPU thread counts to compare, e.g. 1,2")
    p.add_argument("--repeats", type=int, help="timed runs per measurement (best kept)")
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--torch-threads", type=int, default=None, help="torch intra-op threads (default 1)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON result here")
    p.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test, not a measurement)")
    a = p.parse_args(argv)
    cfg = TracerBenchmarkConfig.quick() if a.quick else TracerBenchmarkConfig()
    for arg, name in (("sizes", "sizes"), ("res", "resolutions"), ("threads", "threads"), ("repeats", "repeats"),
                      ("device", "device"), ("seed", "seed"), ("torch_threads", "torch_threads")):
        if getattr(a, arg) is not None:
            setattr(cfg, name, getattr(a, arg))
    cfg.__post_init__()
    return a.what, cfg, a.out


def write_json_atomic(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def main(argv=None) -> int:
    _, cfg, out = parse_args(argv)
    result = run_tracer_benchmark(cfg, progress=lambda m: print(m, file=sys.stderr, flush=True))
    print(format_table(result))
    if out is not None:
        write_json_atomic(out, result)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
