"""Edits of a scene spec (for ground-truth re-renders of edited scenes).

An edit list is a list of mappings, each with ``op`` and ``object`` (an object name):

    {op: translate, object: NAME, offset: [x, y, z]}
    {op: rotate, object: NAME, axis: [x, y, z], angle: DEG}   # about the object's origin (its translation)
    {op: scale, object: NAME, factor: S | [sx, sy, sz]}      # in object space
    {op: duplicate, object: NAME, new_name: NAME2, offset: [x, y, z]}
    {op: set_roughness, object: NAME, value: R}              # principled / conductor; 0 = smooth conductor
    {op: set_f0, object: NAME, value: F | [r, g, b]}
    {op: delete, object: NAME}
    {op: set_material, object: NAME, material: {type: ..., ...}}  # replaces the material (as in objects:)

``set_f0`` by material (the F0 buffer is (1 - metallic) 0.08 specular + metallic base_color):

* ``conductor``: specular_reflectance = F0 / F0(eta, k) (perfect mirror: = F0), so the
  reflectance at normal incidence becomes F0 (must stay <= 1).
* ``principled`` with metallic = 1: base_color = F0 (a texture is dropped).
* ``principled`` with metallic = 0: specular = F0 / 0.08 (a scalar F0 <= 0.08; an RGB
  value must be grey).
* other materials: ValueError.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .mitsuba_scene import conductor_f0
from .spec import ObjectSpec, SynthSpec, _keys, _num, _vec, parse_material

OPS = ("translate", "rotate", "scale", "duplicate", "set_roughness", "set_f0", "delete", "set_material")
_OP_KEYS = {
    "translate": {"offset"}, "rotate": {"axis", "angle"}, "scale": {"factor"},
    "duplicate": {"new_name", "offset"}, "set_roughness": {"value"}, "set_f0": {"value"}, "delete": set(),
    "set_material": {"material"},
}


def _replace_object(spec: SynthSpec, name: str, new: ObjectSpec | None) -> SynthSpec:
    objs = [new if o.name == name else o for o in spec.objects]
    return dataclasses.replace(spec, objects=tuple(o for o in objs if o is not None))


def _set_f0(obj: ObjectSpec, value, where: str) -> ObjectSpec:
    m = obj.material
    f0 = np.asarray(_vec(value, f"{where}.value", 3, 0.0, 1.0))
    if m.type == "conductor":
        base = np.asarray(conductor_f0(dataclasses.replace(m, specular_reflectance=(1.0, 1.0, 1.0))))
        refl = f0 / base
        if np.any(refl > 1.0 + 1e-9):
            raise ValueError(f"{where}.value: F0 {f0.tolist()} exceeds the conductor's own F0 {base.tolist()}")
        m = dataclasses.replace(m, specular_reflectance=tuple(float(x) for x in np.minimum(refl, 1.0)))
    elif m.type == "principled" and m.metallic == 1.0:
        m = dataclasses.replace(m, base_color=tuple(float(x) for x in f0), texture=None)
    elif m.type == "principled" and m.metallic == 0.0:
        if np.ptp(f0) > 1e-9 or f0[0] > 0.08:
            raise ValueError(f"{where}.value: a dielectric principled F0 must be grey and <= 0.08 "
                             f"(0.08 x specular), got {f0.tolist()}")
        m = dataclasses.replace(m, specular=float(f0[0] / 0.08))
    else:
        raise ValueError(f"{where}: set_f0 needs a conductor or a principled material with metallic 0 or 1, "
                         f"object {obj.name!r} is {m.type} (metallic {m.metallic})")
    return dataclasses.replace(obj, material=m)


def apply_scene_edit(spec: SynthSpec, edit: dict, where: str = "edit") -> SynthSpec:
    if not isinstance(edit, dict) or edit.get("op") not in OPS:
        got = edit.get("op") if isinstance(edit, dict) else edit
        raise ValueError(f"{where}.op: must be one of {', '.join(OPS)}, got {got!r}")
    op = edit["op"]
    _keys(edit, where, {"op", "object"} | _OP_KEYS[op], {"op", "object"} | _OP_KEYS[op])
    try:
        obj = spec.object(edit["object"])
    except ValueError as e:
        raise ValueError(f"{where}.object: {e}") from None
    tr = obj.transform
    if op == "translate":
        off = _vec(edit["offset"], f"{where}.offset")
        tr = dataclasses.replace(tr, translate=tuple(a + b for a, b in zip(tr.translate, off)))
        return _replace_object(spec, obj.name, dataclasses.replace(obj, transform=tr))
    if op == "rotate":
        axis = _vec(edit["axis"], f"{where}.axis")
        if not any(axis):
            raise ValueError(f"{where}.axis: must be non-zero")
        tr = dataclasses.replace(tr, rotate=tr.rotate + ((axis, _num(edit["angle"], f"{where}.angle")),))
        return _replace_object(spec, obj.name, dataclasses.replace(obj, transform=tr))
    if op == "scale":
        f = _vec(edit["factor"], f"{where}.factor", 3, 1e-6)
        tr = dataclasses.replace(tr, scale=tuple(a * b for a, b in zip(tr.scale, f)))
        return _replace_object(spec, obj.name, dataclasses.replace(obj, transform=tr))
    if op == "duplicate":
        new_name = edit["new_name"]
        if not isinstance(new_name, str) or not new_name.isidentifier():
            raise ValueError(f"{where}.new_name: must be an identifier-like string, got {new_name!r}")
        if any(o.name == new_name for o in spec.objects):
            raise ValueError(f"{where}.new_name: an object named {new_name!r} already exists")
        off = _vec(edit["offset"], f"{where}.offset")
        tr = dataclasses.replace(tr, translate=tuple(a + b for a, b in zip(tr.translate, off)))
        dup = dataclasses.replace(obj, name=new_name, transform=tr)
        return dataclasses.replace(spec, objects=spec.objects + (dup,))
    if op == "set_roughness":
        if obj.material.type == "diffuse":
            raise ValueError(f"{where}: object {obj.name!r} is diffuse and has no roughness")
        r = _num(edit["value"], f"{where}.value", 0.0, 1.0)
        new = dataclasses.replace(obj, material=dataclasses.replace(obj.material, roughness=r))
        return _replace_object(spec, obj.name, new)
    if op == "set_f0":
        return _replace_object(spec, obj.name, _set_f0(obj, edit["value"], where))
    if op == "set_material":
        material = parse_material(edit["material"], f"{where}.material", spec.textures)
        return _replace_object(spec, obj.name, dataclasses.replace(obj, material=material))
    # delete
    if obj.emitter is not None and sum(o.emitter is not None for o in spec.objects) == 1:
        raise ValueError(f"{where}: cannot delete {obj.name!r}, the scene's only light")
    return _replace_object(spec, obj.name, None)


def apply_edits(spec: SynthSpec, edits: list[dict] | None, where: str = "edits") -> SynthSpec:
    """``spec`` with ``edits`` applied in order (the input is not modified)."""
    if edits is None:
        return spec
    if not isinstance(edits, list):
        raise ValueError(f"{where}: must be a list of edit mappings, got {type(edits).__name__}")
    for i, e in enumerate(edits):
        spec = apply_scene_edit(spec, e, f"{where}[{i}]")
    return spec


__all__ = ["OPS", "apply_edits", "apply_scene_edit"]
