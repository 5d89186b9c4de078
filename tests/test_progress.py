"""stages.progress, the runner every rule starts its stage with: the log gets exactly what the stage wrote, the
console one line per start / end (and progress between), the exit status passes through."""

import io
import subprocess
import sys

from stages import progress

STAGE = r"""
import sys, time
print("loaded", flush=True)
for i in range(3):
    sys.stderr.write(f"\rtrain: {33 * (i + 1)}%|###       | {i + 1}/3 [00:0{i}<00:01, 9.7it/s]")
    sys.stderr.flush()
    time.sleep(0.05)
sys.stderr.write("\n")
if len(sys.argv) > 1:
    print("error: no capture at /nowhere", file=sys.stderr)
    sys.exit(int(sys.argv[1]))
"""


def _run(tmp_path, monkeypatch, *args):
    monkeypatch.setattr(progress, "PLAIN_INTERVAL_S", 0.0)  # every change of progress gets its line
    console = io.StringIO()  # not a terminal: plain lines
    log = tmp_path / "logs" / "stage.log"
    rc = progress.run([sys.executable, "-c", STAGE, *args], log, "reconstruct scene=demo", console)
    return rc, log, console.getvalue().splitlines()


def test_log_is_what_the_stage_wrote_and_console_has_its_lines(tmp_path, monkeypatch):
    rc, log, lines = _run(tmp_path, monkeypatch)
    assert rc == 0
    direct = subprocess.run([sys.executable, "-c", STAGE], capture_output=True, text=True)
    assert log.read_text() == direct.stdout + direct.stderr  # same bytes as `> log 2>&1` (stdout flushed first)
    assert lines[0] == f"[reconstruct scene=demo] started (log: {log})"
    assert lines[-1].startswith("[reconstruct scene=demo] done in ") and lines[-1].endswith(" s")
    shown = [l for l in lines[1:-1] if "train:" in l]
    assert shown, lines
    assert all("|" not in l for l in shown)  # tqdm's bar drawing dropped: "train: 33% 1/3 [...]"


def test_failure_passes_exit_status_and_names_the_error(tmp_path, monkeypatch):
    rc, log, lines = _run(tmp_path, monkeypatch, "3")
    assert rc == 3
    assert lines[-1].startswith("[reconstruct scene=demo] FAILED after ")
    assert "(exit 3): error: no capture at /nowhere" in lines[-1] and str(log) in lines[-1]


def test_compact_and_last_segment():
    bar = "\rrender test:  50%|█████     | 1/2 [00:03<00:03,  3.10s/view]"
    assert progress.last_segment("x\n" + bar * 2) == bar[1:]
    assert progress.compact(bar[1:]) == "render test: 50% 1/2 [00:03<00:03, 3.10s/view]"
    assert progress.compact("a" * 50, width=10) == "aaaaaaa..."
    assert progress.last_error("INFO x\nerror: bad value\nTraceback\n") == "error: bad value"
