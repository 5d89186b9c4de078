"""Stage outputs that are either complete or absent.

A stage writes its output folder through :func:`staged_folder`: everything goes into a hidden sibling
``.<name>.partial`` and only a run that finishes renames it to ``<name>`` (the previous output, if any, is
replaced in one step). A killed run leaves no mix of new and old files at the output path; a run that fails
(an error, a full disk) removes what it wrote. Single files go through :func:`replace_file` (write a temporary
sibling, then rename). :func:`run_stage` turns a full disk into one line naming the path.
"""

from __future__ import annotations

import errno
import os
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def partial_path(out: Path) -> Path:
    """Where a stage writes ``out`` until it has finished."""
    return out.with_name(f".{out.name}.partial")


@contextmanager
def staged_folder(out: str | Path, resume: bool = False) -> Iterator[Path]:
    """Yield the folder to write ``out``'s contents into; on success it becomes ``out``. ``resume``: keep what
    an interrupted run left in the partial folder (stages that skip finished work, e.g. synth's views);
    otherwise it starts empty. On an exception the partial folder is removed (unless ``resume``, where only a
    full disk removes it) and ``out`` is left as it was."""
    out = Path(out)
    tmp = partial_path(out)
    if tmp.exists() and not resume:
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        yield tmp
    except BaseException as e:
        if not resume or (isinstance(e, OSError) and e.errno in NO_SPACE):
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = out.with_name(f".{out.name}.old")
    if out.exists():
        if old.exists():
            shutil.rmtree(old)
        os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)


def replace_file(path: str | Path, write: Callable[[Path], object]) -> Path:
    """``write(tmp)`` into a temporary sibling of ``path``, then rename it to ``path`` (removed on failure)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def disk_free_mib(path: Path) -> float | None:
    """Free space (MiB) of the file system holding ``path`` (its nearest existing parent), or None."""
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    try:
        return shutil.disk_usage(path).free / 2**20
    except OSError:
        return None


def run_stage(main: Callable[[], int]) -> int:
    """Run a stage's ``main``; a full disk (or quota) becomes one ``error:`` line naming the file and the free
    space, exit code 1 (the stage's partial output is already removed by :func:`staged_folder`)."""
    try:
        return main()
    except OSError as e:
        if e.errno not in NO_SPACE:
            raise
        where = e.filename or "the output"
        free = disk_free_mib(Path(e.filename)) if e.filename else None
        room = f" ({free:.1f} MiB free there)" if free is not None else ""
        print(f"error: no space left on the device while writing {where}{room}; nothing was kept of this "
              "stage's output. Free some space (or write elsewhere) and run it again.", file=sys.stderr)
        return 1
