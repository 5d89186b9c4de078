"""Typed scene spec of the ``synth:`` config section, parsed from plain dicts (YAML / JSON).

Every user mistake raises ``ValueError`` naming the key path and the bad value,
e.g. ``synth.objects[2].material.roughness: must be in [0, 1], got 1.5``.
The JSON schema ``workflow/schemas/synth.schema.yaml`` describes the same layout;
this parser is the authority (it also checks cross references such as texture names).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

SHAPES = ("sphere", "cube", "rectangle", "disk", "cylinder")
MATERIALS = ("diffuse", "principled", "conductor")
TEXTURE_TYPES = ("noise", "checker")
PATH_TYPES = ("orbit", "list")

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class TextureSpec:
    """A procedural RGB texture generated in numpy (``textures.py``) with its own seed."""

    name: str
    type: str  # noise | checker
    size: int = 256  # bitmap side in texels
    seed: int = 0
    scale: float = 8.0  # noise: cells across the base octave; checker: checks per side
    octaves: int = 4  # noise: number of octaves
    colors: tuple[Vec3, ...] = ((0.1, 0.1, 0.1), (0.8, 0.8, 0.8))  # palette the texture maps into
    detail: float = 0.25  # amplitude of per-texel high-frequency variation (features for SfM)


@dataclass(frozen=True)
class MaterialSpec:
    """Material of one object. Roughness is perceptual: GGX alpha = roughness**2."""

    type: str  # diffuse | principled | conductor
    base_color: Vec3 = (0.5, 0.5, 0.5)  # diffuse reflectance / principled base colour (if no texture)
    texture: str | None = None  # name of a texture replacing base_color
    roughness: float = 0.5  # principled / conductor (0 = smooth conductor)
    metallic: float = 0.0  # principled
    specular: float = 0.5  # principled (F0 of the dielectric part = 0.08 * specular)
    specular_reflectance: Vec3 = (1.0, 1.0, 1.0)  # conductor: tint of the Fresnel term
    eta: Vec3 | None = None  # conductor: complex IOR (RGB); None with k None = perfect mirror (F = 1)
    k: Vec3 | None = None


@dataclass(frozen=True)
class TransformSpec:
    """to_world = translate @ rotate[-1] @ ... @ rotate[0] @ scale (rotations about the object origin)."""

    translate: Vec3 = (0.0, 0.0, 0.0)
    rotate: tuple[tuple[Vec3, float], ...] = ()  # (axis, angle in degrees), applied in order
    scale: Vec3 = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    shape: str  # sphere (unit radius) | cube ([-1,1]^3) | rectangle ([-1,1]^2, normal +z) | disk | cylinder
    material: MaterialSpec
    transform: TransformSpec = TransformSpec()
    emitter: Vec3 | None = None  # area-light radiance (RGB), None = not a light


@dataclass(frozen=True)
class CameraPathSpec:
    """A camera path: ``orbit`` around a target or an explicit ``list`` of (position, target)."""

    type: str
    count: int
    fov_y: float = 50.0  # vertical field of view, degrees
    target: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 3.0  # orbit: horizontal distance to the target
    height: tuple[float, float] = (1.0, 1.0)  # orbit: camera y, first and last view (linear)
    azimuth: tuple[float, float] = (0.0, 360.0)  # orbit: degrees, 0 = on +z of target, first and last view
    views: tuple[tuple[Vec3, Vec3], ...] = ()  # list: (position, target) per view


@dataclass(frozen=True)
class SynthSpec:
    resolution: tuple[int, int]  # (W, H)
    spp: int
    objects: tuple[ObjectSpec, ...]
    train: CameraPathSpec
    test: CameraPathSpec
    textures: dict[str, TextureSpec] = field(default_factory=dict)
    seed: int = 0
    max_depth: int = 5  # scattering vertices per path (first hit included)
    spp_chunk: int = 64  # samples per pixel traced per wavefront pass (memory bound)
    denoise: bool = False  # OIDN on diffuse / specular (render.denoise_view); rgb = their sum + emission

    def object(self, name: str) -> ObjectSpec:
        for obj in self.objects:
            if obj.name == name:
                return obj
        raise ValueError(f"no object named {name!r} (objects: {', '.join(o.name for o in self.objects)})")


# ---------------------------------------------------------------------------------------------
# parsing helpers


def _keys(d: Any, where: str, allowed: set[str], required: set[str] = frozenset()) -> dict:
    if not isinstance(d, dict):
        raise ValueError(f"{where}: must be a mapping, got {type(d).__name__} {d!r}")
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))} (allowed: {', '.join(sorted(allowed))})")
    missing = sorted(required - set(d))
    if missing:
        raise ValueError(f"{where}: missing required key(s) {', '.join(map(repr, missing))}")
    return d


def _num(v: Any, where: str, lo: float | None = None, hi: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{where}: must be a number, got {v!r}")
    v = float(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"{where}: must be in [{lo}, {hi}], got {v}")
    return v


def _int(v: Any, where: str, lo: int | None = None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{where}: must be an integer, got {v!r}")
    if lo is not None and v < lo:
        raise ValueError(f"{where}: must be >= {lo}, got {v}")
    return v


def _bool(v: Any, where: str) -> bool:
    if not isinstance(v, bool):
        raise ValueError(f"{where}: must be true or false, got {v!r}")
    return v


def _vec(v: Any, where: str, n: int = 3, lo: float | None = None, hi: float | None = None) -> tuple:
    if isinstance(v, (int, float)) and not isinstance(v, bool) and n == 3:
        v = [v] * 3
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise ValueError(f"{where}: must be a list of {n} numbers, got {v!r}")
    return tuple(_num(x, f"{where}[{i}]", lo, hi) for i, x in enumerate(v))


def _choice(v: Any, where: str, options: tuple[str, ...]) -> str:
    if v not in options:
        raise ValueError(f"{where}: must be one of {', '.join(options)}, got {v!r}")
    return v


# ---------------------------------------------------------------------------------------------


def parse_texture(name: str, d: Any, where: str) -> TextureSpec:
    _keys(d, where, {"type", "size", "seed", "scale", "octaves", "colors", "detail"}, {"type"})
    kw: dict[str, Any] = {"name": name, "type": _choice(d["type"], f"{where}.type", TEXTURE_TYPES)}
    if "size" in d:
        kw["size"] = _int(d["size"], f"{where}.size", 4)
    if "seed" in d:
        kw["seed"] = _int(d["seed"], f"{where}.seed", 0)
    if "scale" in d:
        kw["scale"] = _num(d["scale"], f"{where}.scale", 1.0)
    if "octaves" in d:
        kw["octaves"] = _int(d["octaves"], f"{where}.octaves", 1)
    if "detail" in d:
        kw["detail"] = _num(d["detail"], f"{where}.detail", 0.0, 1.0)
    if "colors" in d:
        cols = d["colors"]
        if not isinstance(cols, list) or len(cols) < 2:
            raise ValueError(f"{where}.colors: must be a list of at least 2 RGB colours, got {cols!r}")
        kw["colors"] = tuple(_vec(c, f"{where}.colors[{i}]", 3, 0.0, 1.0) for i, c in enumerate(cols))
    return TextureSpec(**kw)


def parse_material(d: Any, where: str, textures: dict[str, TextureSpec]) -> MaterialSpec:
    _keys(d, where, {"type", "base_color", "texture", "roughness", "metallic", "specular",
                     "specular_reflectance", "eta", "k"}, {"type"})
    mtype = _choice(d["type"], f"{where}.type", MATERIALS)
    allowed = {
        "diffuse": {"type", "base_color", "texture"},
        "principled": {"type", "base_color", "texture", "roughness", "metallic", "specular"},
        "conductor": {"type", "roughness", "specular_reflectance", "eta", "k"},
    }[mtype]
    bad = sorted(set(d) - allowed)
    if bad:
        raise ValueError(f"{where}: key(s) {', '.join(map(repr, bad))} not valid for a {mtype} material "
                         f"(allowed: {', '.join(sorted(allowed))})")
    kw: dict[str, Any] = {"type": mtype}
    if "base_color" in d:
        kw["base_color"] = _vec(d["base_color"], f"{where}.base_color", 3, 0.0, 1.0)
    if "texture" in d:
        if d["texture"] not in textures:
            raise ValueError(f"{where}.texture: unknown texture {d['texture']!r} "
                             f"(defined: {', '.join(textures) or 'none'})")
        kw["texture"] = d["texture"]
    for key in ("roughness", "metallic", "specular"):
        if key in d:
            kw[key] = _num(d[key], f"{where}.{key}", 0.0, 1.0)
    if mtype == "conductor":
        kw.setdefault("roughness", 0.0)
    if mtype == "principled" and kw.get("metallic", 0.0) > 0 and kw.get("specular", 0.5) == 0:
        raise ValueError(f"{where}: a principled material with metallic > 0 needs specular > 0 "
                         f"(Mitsuba drops its whole specular lobe, metal included, when specular = 0)")
    if "specular_reflectance" in d:
        kw["specular_reflectance"] = _vec(d["specular_reflectance"], f"{where}.specular_reflectance", 3, 0.0, 1.0)
    if ("eta" in d) != ("k" in d):
        raise ValueError(f"{where}: give both 'eta' and 'k' (complex IOR) or neither (perfect mirror)")
    if "eta" in d:
        kw["eta"] = _vec(d["eta"], f"{where}.eta", 3, 1e-3)
        kw["k"] = _vec(d["k"], f"{where}.k", 3, 0.0)
    return MaterialSpec(**kw)


def parse_transform(d: Any, where: str) -> TransformSpec:
    _keys(d, where, {"translate", "rotate", "scale"})
    kw: dict[str, Any] = {}
    if "translate" in d:
        kw["translate"] = _vec(d["translate"], f"{where}.translate")
    if "scale" in d:
        kw["scale"] = _vec(d["scale"], f"{where}.scale", 3, 1e-6)
    if "rotate" in d:
        rots = d["rotate"]
        if isinstance(rots, dict):
            rots = [rots]
        if not isinstance(rots, list):
            raise ValueError(f"{where}.rotate: must be a list of {{axis, angle}} mappings, got {rots!r}")
        out = []
        for i, r in enumerate(rots):
            w = f"{where}.rotate[{i}]"
            _keys(r, w, {"axis", "angle"}, {"axis", "angle"})
            axis = _vec(r["axis"], f"{w}.axis")
            if sum(a * a for a in axis) == 0:
                raise ValueError(f"{w}.axis: must be non-zero, got {list(axis)}")
            out.append((axis, _num(r["angle"], f"{w}.angle")))
        kw["rotate"] = tuple(out)
    return TransformSpec(**kw)


def parse_object(d: Any, where: str, textures: dict[str, TextureSpec]) -> ObjectSpec:
    _keys(d, where, {"name", "shape", "material", "transform", "emitter"}, {"name", "shape", "material"})
    name = d["name"]
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{where}.name: must be an identifier-like string, got {name!r}")
    emitter = None
    if "emitter" in d:
        e = _keys(d["emitter"], f"{where}.emitter", {"radiance"}, {"radiance"})
        emitter = _vec(e["radiance"], f"{where}.emitter.radiance", 3, 0.0)
    return ObjectSpec(
        name=name,
        shape=_choice(d["shape"], f"{where}.shape", SHAPES),
        material=parse_material(d["material"], f"{where}.material", textures),
        transform=parse_transform(d.get("transform", {}), f"{where}.transform"),
        emitter=emitter,
    )


def parse_camera_path(d: Any, where: str) -> CameraPathSpec:
    _keys(d, where, {"type", "count", "fov_y", "target", "radius", "height", "azimuth", "views"}, {"type", "count"})
    ptype = _choice(d["type"], f"{where}.type", PATH_TYPES)
    kw: dict[str, Any] = {"type": ptype, "count": _int(d["count"], f"{where}.count", 0)}
    if "fov_y" in d:
        kw["fov_y"] = _num(d["fov_y"], f"{where}.fov_y", 1.0, 170.0)
    if ptype == "orbit":
        bad = sorted(set(d) & {"views"})
        if bad:
            raise ValueError(f"{where}: 'views' is only valid for type 'list'")
        if "target" in d:
            kw["target"] = _vec(d["target"], f"{where}.target")
        if "radius" in d:
            kw["radius"] = _num(d["radius"], f"{where}.radius", 1e-6)
        if "height" in d:
            h = d["height"]
            kw["height"] = _vec([h, h] if isinstance(h, (int, float)) else h, f"{where}.height", 2)
        if "azimuth" in d:
            kw["azimuth"] = _vec(d["azimuth"], f"{where}.azimuth", 2)
    else:
        bad = sorted(set(d) & {"target", "radius", "height", "azimuth"})
        if bad:
            raise ValueError(f"{where}: key(s) {', '.join(map(repr, bad))} are only valid for type 'orbit'")
        views = d.get("views")
        if not isinstance(views, list) or not views:
            raise ValueError(f"{where}.views: type 'list' needs a non-empty list of {{position, target}}")
        out = []
        for i, v in enumerate(views):
            w = f"{where}.views[{i}]"
            _keys(v, w, {"position", "target"}, {"position", "target"})
            out.append((_vec(v["position"], f"{w}.position"), _vec(v["target"], f"{w}.target")))
        if kw["count"] > len(out):
            raise ValueError(f"{where}.count: {kw['count']} exceeds the {len(out)} listed views")
        kw["views"] = tuple(out)
    return CameraPathSpec(**kw)


def parse_spec(cfg: Any, where: str = "synth") -> SynthSpec:
    """The typed spec of a ``synth:`` section. Raises ValueError naming the bad key/value."""
    _keys(cfg, where, {"seed", "resolution", "spp", "max_depth", "spp_chunk", "denoise", "textures", "objects",
                          "cameras"},
          {"resolution", "spp", "objects", "cameras"})
    textures_raw = cfg.get("textures", {}) or {}
    if not isinstance(textures_raw, dict):
        raise ValueError(f"{where}.textures: must be a mapping name -> texture, got {textures_raw!r}")
    textures = {n: parse_texture(n, t, f"{where}.textures.{n}") for n, t in textures_raw.items()}
    objs_raw = cfg["objects"]
    if not isinstance(objs_raw, list) or not objs_raw:
        raise ValueError(f"{where}.objects: must be a non-empty list, got {objs_raw!r}")
    objects = tuple(parse_object(o, f"{where}.objects[{i}]", textures) for i, o in enumerate(objs_raw))
    names = [o.name for o in objects]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{where}.objects: duplicate object name(s) {', '.join(dup)}")
    if not any(o.emitter for o in objects):
        raise ValueError(f"{where}.objects: the scene needs at least one object with an 'emitter' (area light)")
    res = _vec(cfg["resolution"], f"{where}.resolution", 2, 1)
    if any(r != int(r) for r in res):
        raise ValueError(f"{where}.resolution: must be two integers [W, H], got {cfg['resolution']!r}")
    cams = _keys(cfg["cameras"], f"{where}.cameras", {"train", "test"}, {"train", "test"})
    return SynthSpec(
        resolution=(int(res[0]), int(res[1])),
        spp=_int(cfg["spp"], f"{where}.spp", 1),
        objects=objects,
        train=parse_camera_path(cams["train"], f"{where}.cameras.train"),
        test=parse_camera_path(cams["test"], f"{where}.cameras.test"),
        textures=textures,
        seed=_int(cfg.get("seed", 0), f"{where}.seed", 0),
        max_depth=_int(cfg.get("max_depth", 5), f"{where}.max_depth", 1),
        spp_chunk=_int(cfg.get("spp_chunk", 64), f"{where}.spp_chunk", 1),
        denoise=_bool(cfg.get("denoise", False), f"{where}.denoise"),
    )
