"""Typed spec -> Mitsuba 3 scene dict (built in code), plus the per-shape material table the
split integrator reads at the first hit (layer routing, roughness, F0, principled lobe params)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from .spec import MaterialSpec, ObjectSpec, SynthSpec, TransformSpec
from .textures import make_texture

# Mitsuba's LLVM (CPU) backend; MITSUBA_VARIANT=cuda_ad_rgb renders the same integrator on a GPU (a machine
# without libLLVM, e.g. a lent GPU: .ci/gpu-bench train); the noise differs, not the estimator
VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
VARIANT = os.environ.get("MITSUBA_VARIANT", VARIANTS[0])
if VARIANT not in VARIANTS:
    raise ValueError(f"MITSUBA_VARIANT={VARIANT!r}: expected one of {', '.join(VARIANTS)}")

# Layer routing of a material at the first vertex (see integrator.py).
ROUTE_DIFFUSE = 0  # every first-vertex contribution is diffuse; specular exactly 0
ROUTE_SPECULAR = 1  # every first-vertex contribution is specular; diffuse exactly 0
ROUTE_SPLIT = 2  # principled with both lobes: each lobe evaluated separately (lobes.py)


def mitsuba():
    """The ``mitsuba`` module with the project's variant set (idempotent)."""
    import mitsuba as mi

    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


def _rotation(axis, angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    t = math.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def to_world_matrix(tr: TransformSpec) -> np.ndarray:
    """translate @ rotate[-1] @ ... @ rotate[0] @ scale. # [4, 4] float64"""
    m = np.diag([*tr.scale, 1.0])
    for axis, angle in tr.rotate:
        r = np.eye(4)
        r[:3, :3] = _rotation(axis, angle)
        m = r @ m
    m[:3, 3] += np.asarray(tr.translate)
    return m


@dataclass
class MaterialEntry:
    """What the integrator needs about the material of one shape (all RGB as tuples)."""

    shape_id: str
    route: int  # ROUTE_*
    roughness: float  # roughness buffer value (perceptual)
    f0_const: tuple  # F0 = f0_const + f0_tex_weight * texture
    f0_tex_weight: float
    principled: bool  # needs the recomputed diffuse lobe (ROUTE_SPLIT)
    metallic: float
    specular: float  # principled 'specular' (dielectric F0 = 0.08 specular)
    base_color: tuple  # used when texture is None
    texture: object | None  # mi.Texture (same object the BSDF uses) or None


def conductor_f0(m: MaterialSpec) -> tuple:
    """Reflectance at normal incidence times specular_reflectance (perfect mirror: F = 1)."""
    if m.eta is None:
        base = np.ones(3)
    else:
        eta, k = np.asarray(m.eta), np.asarray(m.k)
        base = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
    return tuple(float(x) for x in base * np.asarray(m.specular_reflectance))


def route_of(m: MaterialSpec) -> int:
    if m.type == "diffuse":
        return ROUTE_DIFFUSE
    if m.type == "conductor":
        return ROUTE_SPECULAR
    # principled: metallic = 1 -> Mitsuba's diffuse weight (1 - metallic) is 0;
    # specular = 0 and metallic = 0 -> eta = 1, dielectric Fresnel 0, no specular lobe.
    if m.metallic == 1.0:
        return ROUTE_SPECULAR
    if m.metallic == 0.0 and m.specular == 0.0:
        return ROUTE_DIFFUSE
    return ROUTE_SPLIT


def _rgb(c) -> dict:
    return {"type": "rgb", "value": [float(x) for x in c]}


def bsdf_dict(m: MaterialSpec, texture) -> dict:
    color = texture if texture is not None else _rgb(m.base_color)
    if m.type == "diffuse":
        return {"type": "diffuse", "reflectance": color}
    if m.type == "principled":
        return {"type": "principled", "base_color": color, "roughness": m.roughness,
                "metallic": m.metallic, "specular": m.specular}
    d: dict = {"specular_reflectance": _rgb(m.specular_reflectance)}
    if m.eta is None:
        d["material"] = "none"
    else:
        d["eta"], d["k"] = _rgb(m.eta), _rgb(m.k)
    if m.roughness == 0.0:
        d["type"] = "conductor"
    else:
        d.update(type="roughconductor", distribution="ggx", alpha=m.roughness**2)
    return d


def material_entry(obj: ObjectSpec, texture) -> MaterialEntry:
    m = obj.material
    route = route_of(m)
    base = tuple(m.base_color)
    if m.type == "diffuse":
        rough, f0, w = 1.0, (0.0, 0.0, 0.0), 0.0
    elif m.type == "conductor":
        rough, f0, w = m.roughness, conductor_f0(m), 0.0
    else:
        rough = m.roughness
        diel = (1 - m.metallic) * 0.08 * m.specular
        if texture is None:
            f0, w = tuple(diel + m.metallic * c for c in base), 0.0
        else:
            f0, w = (diel, diel, diel), m.metallic
    return MaterialEntry(obj.name, route, rough, f0, w, route == ROUTE_SPLIT, m.metallic, m.specular, base,
                         texture if m.type != "conductor" else None)


@dataclass
class BuiltScene:
    scene_dict: dict
    materials: dict  # shape id -> MaterialEntry


def build_scene_dict(spec: SynthSpec) -> BuiltScene:
    """The Mitsuba scene dict of ``spec`` and its material table. Textures are generated once per name."""
    mi = mitsuba()
    textures = {}
    for name, tspec in spec.textures.items():
        texels = make_texture(tspec)
        textures[name] = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(texels), "raw": True,
                                       "filter_type": "bilinear", "wrap_mode": "repeat"})
    d: dict = {"type": "scene"}
    materials = {}
    for obj in spec.objects:
        tex = textures[obj.material.texture] if obj.material.texture else None
        shape = {"type": obj.shape, "to_world": mi.ScalarTransform4f(to_world_matrix(obj.transform)),
                 "bsdf": bsdf_dict(obj.material, tex)}
        if obj.emitter is not None:
            shape["emitter"] = {"type": "area", "radiance": _rgb(obj.emitter)}
        d[obj.name] = shape
        materials[obj.name] = material_entry(obj, tex)
    return BuiltScene(d, materials)


def load_scene(spec: SynthSpec):
    """(mi.Scene, material table)."""
    mi = mitsuba()
    built = build_scene_dict(spec)
    try:
        scene = mi.load_dict(built.scene_dict, optimize=False)  # keep one shape per object (ids)
    except Exception as e:  # Mitsuba raises RuntimeError with its own text
        raise ValueError(f"synth: Mitsuba could not build the scene: {e}") from None
    return scene, built.materials


def first_hits(spec: SynthSpec, origins: np.ndarray, dirs: np.ndarray, eps: float = 0.0) -> tuple[np.ndarray, list[str]]:
    """(distance [N] along each ray to the first surface of ``spec``, inf where none; the object's name per ray, "none"
    where none): Mitsuba's ray casts on the scene's geometry from ``origins`` [N, 3] along unit ``dirs`` [N, 3],
    starting ``eps`` along each ray (distances still from ``origins``)."""
    t, names, _ = surface_hits(spec, origins, dirs, eps)
    return t, names


def surface_hits(spec: SynthSpec, origins: np.ndarray, dirs: np.ndarray, eps: float = 0.0,
                 scene=None) -> tuple[np.ndarray, list[str], np.ndarray]:
    """``first_hits`` plus the unit geometric normal [N, 3] at each hit (zero where none), turned to face the ray.
    ``scene``: ``load_scene(spec)[0]`` when the caller casts several times (else it is built here)."""
    mi = mitsuba()
    if scene is None:
        scene, _ = load_scene(spec)
    dirs = np.asarray(dirs, np.float64)
    o = np.asarray(origins, np.float64) + eps * dirs
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(dirs[:, k].astype(np.float32)) for k in range(3)]))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    t = np.where(valid, np.array(si.t, dtype=np.float64) + eps, np.inf)
    names = np.full(len(o), "none", dtype=object)
    for shape in scene.shapes():
        names[np.array(si.shape == mi.ShapePtr(shape), dtype=bool) & valid] = shape.id()
    n = np.stack([np.array(si.n[k], dtype=np.float64) for k in range(3)], 1)
    n = np.where(valid[:, None], n, 0.0)
    n *= np.where((n * dirs).sum(1, keepdims=True) > 0, -1.0, 1.0)  # facing the ray
    return t, list(names), n
