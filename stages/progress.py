"""``python -m stages.progress --label NAME --log LOG -- CMD ...``: run one workflow job with its whole output in
LOG and a compact account of it on the console.

The workflow's rules run every stage through this, so the console shows, besides Snakemake's job blocks, one line
when a stage starts, its progress (the last tqdm bar or log line it wrote), and one line when it ends with the
elapsed time (on failure: the exit status, the last ``error:`` line and the log's path). On a terminal the
progress line is redrawn in place (at most 4 times a second); otherwise (CI, a pipe, a cluster log) a plain line
is printed at most every ``PLAIN_INTERVAL_S`` seconds, only when the progress changed. The log gets exactly what
the stage wrote (tqdm's ``\\r``-joined bars included), as ``> LOG 2>&1`` gave it.
"""

from __future__ import annotations

import argparse
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TextIO

PLAIN_INTERVAL_S = 20.0  # between progress lines when the console is not a terminal
TTY_INTERVAL_S = 0.25  # between redraws of the in-place line on a terminal
_BAR = re.compile(r"\|[^|]*\|")  # tqdm's bar, between its two pipes
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def compact(segment: str, width: int = 100) -> str:
    """One output segment (a tqdm bar, a log line) as a short single line: bar drawing and colours dropped,
    whitespace collapsed, cut to ``width`` characters."""
    text = " ".join(_BAR.sub(" ", _ANSI.sub("", segment)).split())
    return text if len(text) <= width else text[: max(width - 3, 0)] + "..."


def last_segment(tail: str) -> str:
    """The last non-empty piece of ``tail`` between ``\\r`` / ``\\n``: the latest state of a tqdm bar, or the
    latest line."""
    for piece in reversed(re.split(r"[\r\n]", tail)):
        if piece.strip():
            return piece
    return ""


def last_error(tail: str) -> str:
    """The last line starting with ``error:`` (how the stages report a failure), else the last line."""
    lines = [l.strip() for l in re.split(r"[\r\n]", tail) if l.strip()]
    errors = [l for l in lines if l.startswith("error:")]
    return (errors or lines or [""])[-1]


def elapsed(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 60 else f"{int(seconds // 60)}:{int(seconds % 60):02d} min"


class Console:
    """Where the job's account goes: redraws one line in place on a terminal, prints whole lines otherwise."""

    def __init__(self, label: str, stream: TextIO):
        self.label, self.stream = label, stream
        self.tty = stream.isatty()
        self.partial = False  # an in-place line is on the screen without its newline

    def line(self, text: str) -> None:
        self.stream.write(("\r\x1b[K" if self.partial else "") + f"[{self.label}] {text}\n")
        self.stream.flush()
        self.partial = False

    def progress(self, text: str, seconds: float) -> None:
        if not self.tty:
            self.line(f"{elapsed(seconds)}: {text}")
            return
        head = f"[{self.label} {elapsed(seconds)}] "
        width = shutil.get_terminal_size((100, 24)).columns - 1  # a wrapped line cannot be redrawn in place
        self.stream.write("\r\x1b[K" + head + compact(text, max(width - len(head), 10)))
        self.stream.flush()
        self.partial = True


def run(cmd: list[str], log: Path, label: str, stream: TextIO = sys.stderr) -> int:
    """Run ``cmd`` with stdout and stderr into ``log``; report start, progress and end on ``stream``.
    Returns the command's exit status (128 + N when killed by signal N)."""
    console = Console(label, stream)
    interval = TTY_INTERVAL_S if console.tty else PLAIN_INTERVAL_S
    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    console.line(f"started (log: {log})")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}  # the stage's prints reach the log as they happen
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):  # Snakemake cancelling the job
            signal.signal(sig, lambda signum, _frame: proc.send_signal(signum))
        fd = proc.stdout.fileno()
        tail, shown, next_show = "", "", start + interval
        while True:
            try:
                ready = select.select([fd], [], [], TTY_INTERVAL_S)[0]
            except InterruptedError:
                continue
            if ready:
                chunk = os.read(fd, 1 << 16)
                if not chunk:
                    break
                out.write(chunk)
                out.flush()
                tail = (tail + chunk.decode("utf-8", "replace"))[-8192:]
            now = time.monotonic()
            status = compact(last_segment(tail))
            if status and status != shown and now >= next_show:
                console.progress(status, now - start)
                shown, next_show = status, now + interval
        rc = proc.wait()
    took = elapsed(time.monotonic() - start)
    if rc == 0:
        console.line(f"done in {took}")
        return 0
    rc = 128 - rc if rc < 0 else rc
    console.line(f"FAILED after {took} (exit {rc}): {compact(last_error(tail), 300)} (log: {log})")
    return rc


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m stages.progress", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--label", required=True, help="what the console lines are prefixed with (rule and wildcards)")
    p.add_argument("--log", required=True, type=Path, help="file that gets the command's stdout and stderr")
    p.add_argument("cmd", nargs=argparse.REMAINDER, help="-- then the command to run")
    args = p.parse_args(argv)
    cmd = args.cmd[1:] if args.cmd[:1] == ["--"] else args.cmd
    if not cmd:
        p.error("no command given (after --)")
    return run(cmd, args.log, args.label)


if __name__ == "__main__":
    sys.exit(main())
