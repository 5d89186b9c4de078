"""The editing session behind the viewer: the scene, the edit spec being built, the current selection.
No viser here: the GUI (app.py) and the tests drive the same methods.

The session's edit IS an edit spec (models/editing/spec.py) and the scene shown is always
``apply_edit(original, spec)``, recomputed on every change, so a saved spec replays through the
``edit`` stage to the same Gaussians by construction -- but for the light: the live preview does not relight
(``relight`` traces every Gaussian near the edit, seconds to minutes on a CPU), the stage does, after a move,
duplicate or delete (models/editing/relight.py: shadows follow what casts them). Add ``relight: false`` to the
saved edit to replay the preview bit for bit. Selection rules, those of the spec:

- the first selection used becomes the edit's ``select``: evaluated once on the input model, its
  Gaussians followed through moves (a ``duplicate`` leaves the copies out, a ``delete`` empties it);
- an op on any other selection carries that selection as its own ``select``, evaluated on the model
  as it is when the op runs (a region left behind by a move no longer catches what moved).
"""

from __future__ import annotations

import copy
import logging
import math
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import yaml

from models.capture import Camera
from models.editing import EditSpecError, apply_edit, parse_edit, parse_selection, select, selection_centre
from models.gaussians import Gaussians
from models.tracer import Tracer
from models.trained import ModelSettings

from .progressive import Frame, ProgressiveView, ViewSettings

log = logging.getLogger("stages.view")

MATERIAL_OPS = ("set_roughness", "set_f0", "set_diffuse")  # overwrite ops: a slider drag replaces its last op
ROUND = 6  # decimals kept in saved op parameters (the session applies the rounded values)


def named_selections(edits: dict | None) -> dict[str, dict]:
    """Selection mappings of a scene config's ``edits:``: ``<edit>`` for an edit's ``select``,
    ``<edit>.op<i>`` for an op's own ``select``."""
    out: dict[str, dict] = {}
    for name, edit in (edits or {}).items():
        if not isinstance(edit, dict):
            continue
        if isinstance(edit.get("select"), dict):
            out[name] = copy.deepcopy(edit["select"])
        for i, op in enumerate(edit.get("ops") or []):
            if isinstance(op, dict) and isinstance(op.get("select"), dict):
                out[f"{name}.op{i}"] = copy.deepcopy(op["select"])
    return out


def _r(v):
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_r(x) for x in v]
    return round(float(v), ROUND) + 0.0  # (+ 0.0: no -0.0 in the YAML)


def gizmo_ops(pivot, position, wxyz, tol: float = 1e-6) -> list[dict]:
    """Ops moving what sat at ``pivot`` to a gizmo at ``position`` with orientation ``wxyz`` (it started at
    ``pivot`` with the identity): rotate about the pivot, then translate. Near-identity parts are left out."""
    ops = []
    w, x, y, z = (float(v) for v in wxyz)
    s = math.sqrt(x * x + y * y + z * z)
    angle = math.degrees(2 * math.atan2(s, abs(w)))
    if s > tol and angle > 1e-4:
        axis = np.array([x, y, z]) / s * (1 if w >= 0 else -1)
        ops.append({"op": "rotate", "axis": _r(axis), "angle": _r(angle), "pivot": _r(pivot)})
    offset = np.asarray(position, dtype=np.float64) - np.asarray(pivot, dtype=np.float64)
    if np.abs(offset).max() > tol:
        ops.append({"op": "translate", "offset": _r(offset)})
    return ops


class ViewerSession:
    """The scene being edited (original + edited Gaussians), the edit spec built so far and the current
    selection. Thread-safe: GUI callbacks edit, render threads read ``scene()``."""

    def __init__(self, gaussians: Gaussians, selections: dict[str, dict] | None = None,
                 edits: dict[str, dict] | None = None, name: str = "viewer_edit", device: str = "cpu",
                 threads: int = 2, settings: ViewSettings | None = None, model: ModelSettings | None = None):
        if not isinstance(gaussians, Gaussians):
            raise TypeError(f"gaussians must be a Gaussians, got {type(gaussians).__name__}")
        parse_edit(name, {"ops": [{"op": "delete", "select": {"all": True}}]})  # validates the name
        self.name = name
        # the Gaussians stay where they are (CPU): render_view builds rays and sums on the CPU, and the tracer
        # copies parameters to its device (cuda: BVH and kernels there) and its outputs back
        self.original = gaussians
        # how the model renders (model.yaml: tracer and path settings); the defaults for a bare gaussians.ply
        self.model = model or ModelSettings(source="defaults (no model.yaml given)")
        # one tracer for every view (its BVH follows the edited scene: refit when the count is unchanged,
        # else rebuilt; models/tracer/bvh.py); views take render_lock around a frame
        self.tracer = Tracer(self.model.tracer_config(threads), device=device)
        self.render_lock = threading.Lock()
        self.settings = settings or ViewSettings(max_path_length=self.model.path.max_path_length)
        self.view = self.new_view()
        self.named_edits = copy.deepcopy(edits or {})
        self.selections = dict(selections if selections is not None else named_selections(self.named_edits))
        for key, sel in self.selections.items():
            parse_selection(sel, f"selection {key!r}")
        self.selection: dict | None = None  # current selection mapping (edit-spec YAML form)
        self.selection_name = ""
        self._select: dict | None = None  # the edit's own `select`
        self._ops: list[dict] = []  # committed ops (YAML form)
        self._pending: list[dict] = []  # previewed, not committed (gizmo drag)
        self._scene = gaussians
        self._tracked: torch.Tensor | None = None  # [N] bool, the edit's selection followed through the ops
        self.version = 0
        self.changed_at = time.perf_counter()
        self.last_report: list[dict] = []
        self._lock = threading.RLock()
        self._listeners: list[Callable[[], None]] = []

    # ------------------------------------------------------------------ rendering
    def new_view(self, settings: ViewSettings | None = None) -> ProgressiveView:
        """A progressive view (own camera, accumulation and settings) sharing this session's tracer."""
        return ProgressiveView(self.tracer, copy.copy(settings or self.settings), self.render_lock,
                               path=self.model.path)

    def set_camera(self, camera: Camera) -> None:
        """Camera of the session's own view (``step``)."""
        self.view.set_camera(camera)

    def step(self) -> Frame | None:
        """One more frame of the session's own view (1 spp, accumulated); None when it would not change."""
        g, version = self.scene()
        return self.view.step(g, version)

    def close(self) -> None:
        self.tracer.close()

    # ------------------------------------------------------------------ reading
    def scene(self) -> tuple[Gaussians, int]:
        """(edited Gaussians, version); the version changes with every edit."""
        with self._lock:
            return self._scene, self.version

    def snapshot(self) -> tuple[Gaussians, int, float]:
        """(edited Gaussians, version, perf_counter time of that change), consistent with each other."""
        with self._lock:
            return self._scene, self.version, self.changed_at

    @property
    def ops(self) -> list[dict]:
        with self._lock:
            return copy.deepcopy(self._ops)

    @property
    def pending(self) -> list[dict]:
        with self._lock:
            return copy.deepcopy(self._pending)

    def on_change(self, callback: Callable[[], None]) -> None:
        """Call ``callback()`` after every change of the scene or the selection."""
        self._listeners.append(callback)

    def _notify(self) -> None:
        for cb in list(self._listeners):
            cb()

    # ------------------------------------------------------------------ selection
    def select(self, name: str) -> int:
        """Make the named selection (scene config) current; returns how many Gaussians it catches now."""
        if name not in self.selections:
            raise ValueError(f"unknown selection {name!r} (known: {', '.join(self.selections) or 'none'})")
        return self.select_mapping(self.selections[name], name)

    def select_box(self, lo, hi) -> int:
        """Make the axis-aligned box [lo, hi] (on the Gaussian means) current."""
        lo, hi = _r(lo), _r(hi)
        return self.select_mapping({"box": {"min": lo, "max": hi}}, "(box)")

    def select_mapping(self, sel: dict, name: str = "custom") -> int:
        parse_selection(sel, f"selection {name!r}")
        with self._lock:
            self.selection, self.selection_name = copy.deepcopy(sel), name
            if self._pending:  # a preview belongs to the selection it moved
                self._commit(self._select if self._ops else None, self._ops, [])
            n = int(self.selection_mask().sum())
        self._notify()
        return n

    def selection_mask(self) -> torch.Tensor:
        """[N] bool over the edited scene: what an op on the current selection would change now."""
        with self._lock:
            if self.selection is None:
                return torch.zeros(len(self._scene), dtype=torch.bool, device=self._scene.device)
            if self.selection == self._select and self._tracked is not None:
                return self._tracked
            return select(self._scene, parse_selection(self.selection, "selection"))

    def selected_means(self) -> np.ndarray:
        """[M, 3] float32 means of the selected Gaussians of the edited scene (mask and scene of one version)."""
        with self._lock:
            return self._scene.means.detach()[self.selection_mask()].float().cpu().numpy()

    def selection_centre(self) -> np.ndarray | None:
        """Centre of the bounds of the selected means (the default pivot), or None when nothing is selected."""
        with self._lock:
            mask = self.selection_mask()
            if not bool(mask.any()):
                return None
            return selection_centre(self._scene, mask).double().cpu().numpy()

    def selection_stats(self) -> dict | None:
        """Mean roughness, F0 and diffuse of the selection (to initialise the material sliders)."""
        with self._lock:
            mask = self.selection_mask()
            if not bool(mask.any()):
                return None
            g = self._scene
            return {"count": int(mask.sum()), "roughness": float(g.roughness[mask].mean()),
                    "f0": g.f0[mask].mean(0).tolist(), "diffuse": g.diffuse[mask].mean(0).tolist()}

    # ------------------------------------------------------------------ editing
    def _place(self, op: dict) -> tuple[dict | None, dict]:
        """(the edit's select, the op in YAML form) for ``op`` on the current selection."""
        if not isinstance(op, dict) or "op" not in op:
            raise ValueError(f"an op is a mapping with an 'op' key, got {op!r}")
        op = {k: v for k, v in op.items() if k != "select"}
        sel = self.selection
        if sel is None:
            raise ValueError("pick a selection first (a named selection or a box)")
        edit_select = self._select if (self._select is not None or self._ops) else sel
        if sel != edit_select:
            op["select"] = copy.deepcopy(sel)
        return edit_select, op

    def apply(self, op: dict, coalesce: bool = False) -> list[dict]:
        """Append ``op`` (an edit-spec op mapping without ``select``) on the current selection and update the
        scene; ``coalesce``: replace the last op instead when it is the same material op on the same
        selection (slider drags). Returns apply_edit's per-op report. Raises EditSpecError / ValueError (the
        session is then unchanged)."""
        with self._lock:
            edit_select, placed = self._place(op)
            ops = copy.deepcopy(self._ops)
            last = ops[-1] if ops else None
            if (coalesce and last is not None and placed["op"] in MATERIAL_OPS and last["op"] == placed["op"]
                    and last.get("select") == placed.get("select")):
                ops[-1] = placed
            else:
                ops.append(placed)
            self._commit(edit_select, ops, [])
            report = self.last_report
        self._notify()
        return report

    def set_pending(self, ops: list[dict]) -> None:
        """Preview ``ops`` (on the current selection) after the committed ones, without committing them."""
        with self._lock:
            placed = [self._place(op) for op in ops]
            edit_select = placed[0][0] if placed else self._select
            self._commit(edit_select if self._ops or placed else None, self._ops, [p for _, p in placed])
        self._notify()

    def commit_pending(self) -> None:
        with self._lock:
            if self._pending:
                self._commit(self._select, self._ops + self._pending, [])
        self._notify()

    def clear_pending(self) -> None:
        with self._lock:
            if self._pending:
                self._commit(self._select if self._ops else None, self._ops, [])
        self._notify()

    def undo(self) -> None:
        """Drop the last committed op (and any preview)."""
        with self._lock:
            ops = self._ops[:-1]
            self._commit(self._select if ops else None, ops, [])
        self._notify()

    def reset(self) -> None:
        """Back to the unedited scene (the selection stays)."""
        with self._lock:
            self._commit(None, [], [])
        self._notify()

    def apply_named_edit(self, name: str) -> list[dict]:
        """Append a named edit of the scene config. On an empty session it becomes exactly that edit; after
        other ops, each of its ops carries its selection (evaluated when the op runs)."""
        if name not in self.named_edits:
            raise ValueError(f"unknown edit {name!r} (known: {', '.join(self.named_edits) or 'none'})")
        raw = copy.deepcopy(self.named_edits[name])
        parse_edit(name, raw)  # its own errors first, named
        with self._lock:
            if not self._ops:
                edit_select = raw.get("select")
                ops = [{k: v for k, v in op.items()} for op in raw["ops"]]
            else:
                edit_select, ops = self._select, copy.deepcopy(self._ops)
                for op in raw["ops"]:
                    sel = op.get("select", raw.get("select"))
                    op = {k: v for k, v in op.items() if k != "select"}
                    ops.append(op if sel == edit_select else {**op, "select": sel})
            self._commit(edit_select, ops, [])
            if raw.get("select") is not None:
                self.selection, self.selection_name = copy.deepcopy(raw["select"]), name
            report = self.last_report
        self._notify()
        return report

    def _mapping(self, edit_select: dict | None, ops: list[dict]) -> dict:
        out: dict = {"description": f"edited in the viewer (python -m stages.view), {len(ops)} op(s)"}
        if edit_select is not None:
            out["select"] = copy.deepcopy(edit_select)
        out["ops"] = copy.deepcopy(ops)
        return out

    def _commit(self, edit_select: dict | None, ops: list[dict], pending: list[dict]) -> None:
        """Recompute the scene for these ops; on any error nothing changes."""
        every = list(ops) + list(pending)
        if every:
            spec = parse_edit(self.name, self._mapping(edit_select, every))
            scene, report = apply_edit(self.original, spec)
            tracked = self._follow(spec) if edit_select is not None else None
        else:
            scene, report, tracked = self.original, [], None
        self._select = copy.deepcopy(edit_select) if every else None
        self._ops, self._pending = copy.deepcopy(list(ops)), copy.deepcopy(list(pending))
        self._scene, self.last_report, self._tracked = scene, report, tracked
        self.version += 1
        self.changed_at = time.perf_counter()

    def _follow(self, spec) -> torch.Tensor | None:
        """[N'] bool over the edited scene: the Gaussians of the edit's selection after the ops, as apply_edit
        tracks them. Found by editing a probe whose opacity logits are the Gaussian indices (no op changes
        opacity; copies are appended after their originals, so the first occurrence of an index is the original)."""
        g = self.original
        n = len(g)
        if n >= 2 ** 24:
            return None  # indices no longer exact in float32
        probe = Gaussians(**{**{k: v.detach() for k, v in g.params().items()},
                             "opacity_logits": torch.arange(n, dtype=g.dtype, device=g.device)})
        out, _ = apply_edit(probe, spec)
        idx = out.opacity_logits.round().long().cpu()
        if not bool(((idx >= 0) & (idx < n)).all()):
            return None
        order = torch.arange(len(out))
        first_pos = torch.full((n,), len(out), dtype=torch.long).scatter_reduce(0, idx, order, reduce="amin")
        first = first_pos[idx] == order
        return (first & select(g, spec.select).cpu()[idx]).to(g.device)

    # ------------------------------------------------------------------ saving
    def spec_mapping(self) -> dict:
        """The committed edit as its edit-spec mapping (what a scene config's ``edits:`` holds)."""
        with self._lock:
            if not self._ops:
                raise ValueError("nothing to save: no op applied yet")
            return self._mapping(self._select, self._ops)

    def save_spec(self, path: str | Path, view: dict | None = None) -> Path:
        """Write ``{edits: {<name>: <spec>}}`` (+ ``viewer:`` with ``view``, e.g. camera and spp, for the record)
        as YAML, atomically. Replay: ``python -m stages.edit apply --edit-file PATH --edit NAME ...``."""
        path = Path(path)
        doc = {"edits": {self.name: self.spec_mapping()}}
        if view:
            doc["viewer"] = view
        text = (f"# Edit spec saved by the viewer. Replay it:\n#   python -m stages.edit apply --edit-file {path.name} "
                f"--edit {self.name} --model <gaussians.ply> --capture <capture> --out <folder>\n"
                "# or paste the edit under `edits:` of configs/scenes/<scene>.yaml.\n")
        text += yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(text)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        log.info("saved edit %r (%d ops) to %s", self.name, len(doc["edits"][self.name]["ops"]), path)
        return path


__all__ = ["ViewerSession", "EditSpecError", "gizmo_ops", "named_selections"]
