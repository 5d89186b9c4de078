"""Typed edit specs parsed from the scene config's ``edits:`` mapping (YAML / JSON).

A named edit is a list of operations on the Gaussians, each applied to a selection,
plus (synthetic scenes) the same edit of the Mitsuba scene spec as ground truth::

    move_ball:
      description: move the mirror sphere     # optional
      select: {cylinder: {...}, exclude: [...]}  # default selection of the ops (optional)
      ops:
        - {op: translate, offset: [0.35, 0, 0.45]}        # uses the edit's select
        - {op: set_roughness, value: 0.1, select: {...}}  # its own selection
        - {op: set_albedo, value: [0.8, 0.6, 0.1]}        # Lambertian albedo (traced; samples: 64 rays each)
      relight: auto                            # the light follows the edit (relight.py): auto | true | false
      ground_truth:                            # models/synth/edits.py ops, by object name
        - {op: translate, object: mirror_ball, offset: [0.35, 0, 0.45]}

Selection (every criterion given must hold; then every ``exclude`` selection is removed):

    box:      {min: [x, y, z], max: [x, y, z]}            axis-aligned, on the Gaussian means
    sphere:   {centre: [x, y, z], radius: r}
    cylinder: {centre: [x, y, z], axis: [x, y, z], radius: r, height: h}  centre of the axis segment
    roughness / f0 / diffuse: {min: v, max: v}   stored values (perceptual roughness, F0, linear
              diffuse); for RGB fields a number bounds the channel mean, a list bounds each channel
    all: true                                    every Gaussian
    exclude:  [selection, ...]                   Gaussians caught by any of these are dropped

The edit's ``select`` is evaluated once, on the input model: ops without their own ``select`` apply to
those Gaussians (a ``duplicate`` leaves its copies out of it, a ``delete`` empties it). An op's own
``select`` is evaluated on the model as it is when the op runs (after the earlier ops).
Every mistake raises ``EditSpecError`` naming the edit, the op and the bad key / value.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

Vec3 = tuple[float, float, float]

SELECT_FIELDS = ("box", "sphere", "cylinder", "roughness", "f0", "diffuse", "all", "exclude")
# op -> (required parameters, optional parameters)
OPS: dict[str, tuple[frozenset, frozenset]] = {
    "translate": (frozenset({"offset"}), frozenset()),
    "rotate": (frozenset({"axis", "angle"}), frozenset({"pivot"})),
    "scale": (frozenset({"factor"}), frozenset({"pivot"})),
    "duplicate": (frozenset({"offset"}), frozenset()),
    "delete": (frozenset(), frozenset()),
    "set_roughness": (frozenset({"value"}), frozenset()),
    "shift_roughness": (frozenset({"delta"}), frozenset()),
    "multiply_roughness": (frozenset({"factor"}), frozenset()),
    "set_f0": (frozenset({"value"}), frozenset()),
    "set_diffuse": (frozenset({"value"}), frozenset()),
    "shift_diffuse_hsv": (frozenset(), frozenset({"hue", "saturation", "value"})),
    "set_albedo": (frozenset({"value"}), frozenset({"samples"})),
}
ALBEDO_SAMPLES = 64  # set_albedo: default cosine-distributed rays per Gaussian
EDIT_KEYS = ("description", "select", "ops", "ground_truth", "truth", "relight")


class EditSpecError(ValueError):
    """A bad edit spec; the message names the edit, op and key."""


@dataclass(frozen=True)
class Range:
    """Bounds on a stored value: None = open; a 3-tuple bounds each channel, a float the channel mean."""

    min: float | Vec3 | None = None
    max: float | Vec3 | None = None


@dataclass(frozen=True)
class Cylinder:
    centre: Vec3  # centre of the axis segment
    axis: Vec3  # unit
    radius: float
    height: float  # full length along the axis


@dataclass(frozen=True)
class Selection:
    box: tuple[Vec3, Vec3] | None = None  # (min, max)
    sphere: tuple[Vec3, float] | None = None  # (centre, radius)
    cylinder: Cylinder | None = None
    roughness: Range | None = None
    f0: Range | None = None
    diffuse: Range | None = None
    all: bool = False
    exclude: tuple["Selection", ...] = ()
    text: str = field(default="", compare=False)  # the spec as given (compact JSON), for messages


@dataclass(frozen=True)
class Op:
    kind: str  # one of OPS
    select: Selection | None  # None: the edit's selection
    params: dict  # parsed parameters (floats / 3-tuples); see ops.py


@dataclass(frozen=True)
class EditSpec:
    name: str
    ops: tuple[Op, ...]
    select: Selection | None = None  # default selection, evaluated once on the input model
    description: str = ""
    ground_truth: tuple[dict, ...] | None = None  # synth edit list (validated by models/synth/edits.py)
    truth: str | None = None  # a capture folder of the edited scene's test views the user already has
    relight: str | bool = "auto"  # the light follows the edit (relight.py): auto | true | false


# --------------------------------------------------------------------------------------- helpers


def _fail(where: str, msg: str) -> EditSpecError:
    return EditSpecError(f"{where}: {msg}")


def _mapping(d: Any, where: str, known: tuple[str, ...] | set[str], what: str = "key") -> dict:
    if not isinstance(d, dict):
        raise _fail(where, f"must be a mapping, got {type(d).__name__} {d!r}")
    unknown = sorted(set(d) - set(known))
    if unknown:
        raise _fail(where, f"unknown {what}(s) {', '.join(map(repr, unknown))} (known: {', '.join(sorted(known))})")
    return d


def _num(v: Any, where: str, lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _fail(where, f"must be a finite number, got {v!r}")
    v = float(v)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise _fail(where, f"must be {'>' if lo_open else '>='} {lo}, got {v}")
    if hi is not None and v > hi:
        raise _fail(where, f"must be <= {hi}, got {v}")
    return v


def _vec(v: Any, where: str, lo: float | None = None, hi: float | None = None) -> Vec3:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise _fail(where, f"must be a list of 3 numbers, got {v!r}")
    return tuple(_num(x, f"{where}[{i}]", lo, hi) for i, x in enumerate(v))


def _scalar_or_rgb(v: Any, where: str, lo: float | None = None, hi: float | None = None) -> float | Vec3:
    if isinstance(v, (list, tuple)):
        return _vec(v, where, lo, hi)
    return _num(v, where, lo, hi)


def _unit(v: Any, where: str) -> Vec3:
    a = _vec(v, where)
    n = math.sqrt(sum(x * x for x in a))
    if n == 0:
        raise _fail(where, f"must be non-zero, got {list(a)}")
    return tuple(x / n for x in a)


# --------------------------------------------------------------------------------------- parsing


def _range(d: Any, where: str, rgb: bool) -> Range:
    _mapping(d, where, ("min", "max"))
    if not d:
        raise _fail(where, "give 'min', 'max' or both")
    parse = (lambda v, w: _scalar_or_rgb(v, w)) if rgb else (lambda v, w: _num(v, w))
    return Range(**{k: parse(d[k], f"{where}.{k}") for k in ("min", "max") if k in d})


def parse_selection(d: Any, where: str) -> Selection:
    _mapping(d, where, SELECT_FIELDS, "selection field")
    kw: dict[str, Any] = {}
    if "box" in d:
        b = _mapping(d["box"], f"{where}.box", ("min", "max"))
        if set(b) != {"min", "max"}:
            raise _fail(f"{where}.box", "needs both 'min' and 'max'")
        lo, hi = _vec(b["min"], f"{where}.box.min"), _vec(b["max"], f"{where}.box.max")
        if any(a > c for a, c in zip(lo, hi)):
            raise _fail(f"{where}.box", f"min {list(lo)} exceeds max {list(hi)}")
        kw["box"] = (lo, hi)
    if "sphere" in d:
        s = _mapping(d["sphere"], f"{where}.sphere", ("centre", "radius"))
        if set(s) != {"centre", "radius"}:
            raise _fail(f"{where}.sphere", "needs 'centre' and 'radius'")
        kw["sphere"] = (_vec(s["centre"], f"{where}.sphere.centre"),
                        _num(s["radius"], f"{where}.sphere.radius", 0.0, lo_open=True))
    if "cylinder" in d:
        w = f"{where}.cylinder"
        c = _mapping(d["cylinder"], w, ("centre", "axis", "radius", "height"))
        missing = sorted({"centre", "axis", "radius", "height"} - set(c))
        if missing:
            raise _fail(w, f"missing {', '.join(map(repr, missing))}")
        kw["cylinder"] = Cylinder(_vec(c["centre"], f"{w}.centre"), _unit(c["axis"], f"{w}.axis"),
                                  _num(c["radius"], f"{w}.radius", 0.0, lo_open=True),
                                  _num(c["height"], f"{w}.height", 0.0, lo_open=True))
    if "roughness" in d:
        kw["roughness"] = _range(d["roughness"], f"{where}.roughness", rgb=False)
    for key in ("f0", "diffuse"):
        if key in d:
            kw[key] = _range(d[key], f"{where}.{key}", rgb=True)
    if "all" in d:
        if d["all"] is not True:
            raise _fail(f"{where}.all", f"must be true (leave it out otherwise), got {d['all']!r}")
        kw["all"] = True
    if "exclude" in d:
        ex = d["exclude"]
        if not isinstance(ex, list) or not ex:
            raise _fail(f"{where}.exclude", f"must be a non-empty list of selections, got {ex!r}")
        kw["exclude"] = tuple(parse_selection(e, f"{where}.exclude[{i}]") for i, e in enumerate(ex))
    if not set(kw) - {"exclude"}:
        raise _fail(where, f"selects nothing by itself: give at least one of "
                    f"{', '.join(f for f in SELECT_FIELDS if f != 'exclude')}")
    return Selection(**kw, text=json.dumps(d, separators=(",", ":")))


def parse_op(d: Any, where: str, has_default: bool) -> Op:
    if not isinstance(d, dict):
        raise _fail(where, f"must be a mapping with an 'op' key, got {d!r}")
    kind = d.get("op")
    if kind not in OPS:
        raise _fail(where, f"unknown op {kind!r} (known ops: {', '.join(OPS)})")
    where = f"{where} ({kind})"
    required, optional = OPS[kind]
    _mapping(d, where, {"op", "select"} | required | optional)
    missing = sorted(required - set(d))
    if missing:
        raise _fail(where, f"missing {', '.join(map(repr, missing))}")
    if "select" not in d and not has_default:
        raise _fail(where, "no selection: give 'select' in the op or in the edit")
    p: dict[str, Any] = {}
    if kind in ("translate", "duplicate"):
        p["offset"] = _vec(d["offset"], f"{where}.offset")
    elif kind == "rotate":
        p["axis"] = _unit(d["axis"], f"{where}.axis")
        p["angle"] = _num(d["angle"], f"{where}.angle")
        p["pivot"] = _vec(d["pivot"], f"{where}.pivot") if "pivot" in d else None
    elif kind == "scale":
        p["factor"] = _num(d["factor"], f"{where}.factor", 0.0, lo_open=True)
        p["pivot"] = _vec(d["pivot"], f"{where}.pivot") if "pivot" in d else None
    elif kind == "set_roughness":
        p["value"] = _num(d["value"], f"{where}.value", 0.0, 1.0)
    elif kind == "shift_roughness":
        p["delta"] = _num(d["delta"], f"{where}.delta", -1.0, 1.0)
    elif kind == "multiply_roughness":
        p["factor"] = _num(d["factor"], f"{where}.factor", 0.0)
    elif kind == "set_f0":
        p["value"] = _scalar_or_rgb(d["value"], f"{where}.value", 0.0, 1.0)
    elif kind == "set_diffuse":
        p["value"] = _vec(d["value"], f"{where}.value", 0.0)
    elif kind == "set_albedo":  # Lambertian albedo; the diffuse radiance is traced (albedo.py)
        p["value"] = _vec(d["value"], f"{where}.value", 0.0, 1.0)
        samples = d.get("samples", ALBEDO_SAMPLES)
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise _fail(f"{where}.samples", f"must be an integer >= 1, got {samples!r}")
        p["samples"] = samples
    elif kind == "shift_diffuse_hsv":
        if not set(d) & optional:
            raise _fail(where, "give at least one of 'hue' (degrees), 'saturation', 'value' (factors)")
        p["hue"] = _num(d.get("hue", 0.0), f"{where}.hue")
        p["saturation"] = _num(d.get("saturation", 1.0), f"{where}.saturation", 0.0)
        p["value"] = _num(d.get("value", 1.0), f"{where}.value", 0.0)
    return Op(kind, parse_selection(d["select"], f"{where}.select") if "select" in d else None, p)


def parse_edit(name: str, d: Any) -> EditSpec:
    """One named edit (a value of the config's ``edits:`` mapping)."""
    where = f"edit {name!r}"
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "_-" for c in name):
        raise _fail(where, "the name must be letters, digits, '_' or '-' (it is a folder name)")
    _mapping(d, where, EDIT_KEYS)
    ops = d.get("ops")
    if not isinstance(ops, list) or not ops:
        raise _fail(f"{where}.ops", f"must be a non-empty list of ops, got {ops!r}")
    select = parse_selection(d["select"], f"{where}.select") if "select" in d else None
    parsed = tuple(parse_op(o, f"{where} op {i}", select is not None) for i, o in enumerate(ops))
    gt = d.get("ground_truth")
    if gt is not None:
        if not isinstance(gt, list) or not all(isinstance(e, dict) for e in gt):
            raise _fail(f"{where}.ground_truth", f"must be a list of synth edit mappings, got {gt!r}")
        gt = tuple(gt)
    desc = d.get("description", "")
    if not isinstance(desc, str):
        raise _fail(f"{where}.description", f"must be a string, got {desc!r}")
    truth = d.get("truth")
    if truth is not None and (not isinstance(truth, str) or not truth):
        raise _fail(f"{where}.truth", f"must be the path of a capture folder, got {truth!r}")
    relight = d.get("relight", "auto")
    if not (isinstance(relight, bool) or relight == "auto"):
        raise _fail(f"{where}.relight", f"must be auto, true or false (the light follows the edit: shadows move with "
                                        f"what casts them), got {relight!r}")
    return EditSpec(name=name, ops=parsed, select=select, description=desc, ground_truth=gt, truth=truth,
                    relight=relight)


def parse_edits(d: Any, where: str = "edits") -> dict[str, EditSpec]:
    """The whole ``edits:`` mapping: name -> EditSpec."""
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise _fail(where, f"must be a mapping of named edits, got {type(d).__name__}")
    return {name: parse_edit(name, e) for name, e in d.items()}
