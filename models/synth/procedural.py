"""Random synthetic rooms as training data for the buffer network.

``random_scene_config(seed)`` builds a valid ``synth:`` section (``spec.py``): a closed room (floor,
ceiling, four walls with random textures and colours), 1-2 area lights on the ceiling, 2-6 objects
(spheres and cubes on the floor, rectangles hung on the walls) with random transforms and materials that
span the buffers (textured / plain diffuse; principled with roughness 0.05..1, metallic 0 or 1 and random
base colours; smooth and rough conductors), and an orbit of cameras inside the room looking at its middle.
Every scene has at least one metallic object and one dielectric one. The same seed gives the same config.

Rendering them into capture folders is the synth stage's ``procedural`` command (``stages/synth/procedural.py``).
"""

from __future__ import annotations

import math

import numpy as np

# Complex IOR (eta, k) at R, G, B of common metals.
METALS = {
    "gold": ((0.143, 0.374, 1.442), (3.983, 2.386, 1.603)),
    "copper": ((0.200, 0.924, 1.102), (3.912, 2.452, 2.142)),
    "silver": ((0.155, 0.117, 0.138), (4.828, 3.122, 2.147)),
    "aluminium": ((1.657, 0.880, 0.521), (9.224, 6.270, 4.837)),
}
OBJECT_MATERIALS = ("diffuse_textured", "diffuse", "principled", "principled_metal", "conductor")
OBJECT_WEIGHTS = (0.2, 0.1, 0.3, 0.2, 0.2)
MAX_OBJECT_TOP = 1.0  # highest point of a floor object (m); cameras stay above it
MIN_CAMERA_HEIGHT = 1.25


def _r(x: float) -> float:
    return round(float(x), 4)


def _rgb(values) -> list[float]:
    return [_r(v) for v in values]


class _Builder:
    """Accumulates the textures and objects of one random scene."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.textures: dict[str, dict] = {}
        self.objects: list[dict] = []

    def colour(self, lo: float = 0.05, hi: float = 0.9) -> list[float]:
        return _rgb(self.rng.uniform(lo, hi, 3))

    def texture(self) -> str:
        rng = self.rng
        name = f"tex_{len(self.textures)}"
        kind = str(rng.choice(["checker", "noise"]))
        tex = {"type": kind, "size": 128, "seed": int(rng.integers(0, 2**31 - 1)),
               "colors": [self.colour() for _ in range(int(rng.integers(2, 4)))]}
        if kind == "checker":
            tex["scale"] = int(rng.integers(3, 13))
        else:
            tex.update(scale=_r(rng.uniform(3, 12)), octaves=int(rng.integers(3, 6)))
        self.textures[name] = tex
        return name

    def material(self, kind: str) -> dict:
        rng = self.rng
        if kind == "diffuse_textured":
            return {"type": "diffuse", "texture": self.texture()}
        if kind == "diffuse":
            return {"type": "diffuse", "base_color": self.colour()}
        if kind == "principled":
            m = {"type": "principled", "roughness": _r(rng.uniform(0.05, 1.0)), "metallic": 0.0,
                 "specular": _r(rng.uniform(0.2, 1.0))}
            if rng.random() < 0.4:
                m["texture"] = self.texture()
            else:
                m["base_color"] = self.colour()
            return m
        if kind == "principled_metal":
            return {"type": "principled", "base_color": self.colour(0.4, 1.0), "roughness": _r(rng.uniform(0.05, 0.8)),
                    "metallic": 1.0, "specular": 0.5}
        if kind == "conductor":
            m = {"type": "conductor", "roughness": 0.0 if rng.random() < 0.5 else _r(rng.uniform(0.05, 0.5))}
            if rng.random() < 0.3:  # tinted perfect mirror
                m["specular_reflectance"] = self.colour(0.6, 1.0)
            else:
                eta, k = METALS[str(rng.choice(list(METALS)))]
                m.update(eta=list(eta), k=list(k))
            return m
        raise ValueError(f"unknown material kind {kind!r}")

    def add(self, name: str, shape: str, material: dict, transform: dict, emitter: list | None = None) -> None:
        obj = {"name": name, "shape": shape, "material": material, "transform": transform}
        if emitter is not None:
            obj["emitter"] = {"radiance": emitter}
        self.objects.append(obj)


def _room(b: _Builder, hx: float, hz: float, height: float) -> None:
    rng = b.rng
    floor = (b.material("principled") if rng.random() < 0.7 else b.material("diffuse_textured"))
    floor.pop("base_color", None)
    floor.setdefault("texture", b.texture())
    if floor["type"] == "principled":
        floor["roughness"] = _r(rng.uniform(0.05, 0.8))
    b.add("floor", "rectangle", floor, {"rotate": [{"axis": [1, 0, 0], "angle": -90}], "scale": [_r(hx), _r(hz), 1]})
    b.add("ceiling", "rectangle", {"type": "diffuse", "base_color": b.colour(0.6, 0.9)},
          {"translate": [0, _r(height), 0], "rotate": [{"axis": [1, 0, 0], "angle": 90}], "scale": [_r(hx), _r(hz), 1]})
    walls = {  # name: (translate, rotation about y, half width)
        "wall_back": ([0, height / 2, -hz], 0, hx), "wall_front": ([0, height / 2, hz], 180, hx),
        "wall_left": ([-hx, height / 2, 0], 90, hz), "wall_right": ([hx, height / 2, 0], -90, hz),
    }
    for name, (pos, angle, half) in walls.items():
        m = b.material("diffuse_textured") if rng.random() < 0.8 else b.material("principled")
        if m["type"] == "principled":
            m["roughness"] = _r(rng.uniform(0.4, 1.0))
        b.add(name, "rectangle", m, {"translate": _rgb(pos), "rotate": [{"axis": [0, 1, 0], "angle": angle}],
                                     "scale": [_r(half), _r(height / 2), 1]})


def _lights(b: _Builder, hx: float, hz: float, height: float) -> None:
    rng = b.rng
    for i in range(int(rng.integers(1, 3))):
        sx, sz = rng.uniform(0.2, 0.6, 2)
        x = rng.uniform(-(hx - sx - 0.2), hx - sx - 0.2)
        z = rng.uniform(-(hz - sz - 0.2), hz - sz - 0.2)
        power = rng.uniform(6.0, 20.0)  # radiance x area (the demo room's light: 10)
        tint = np.array([1.0, rng.uniform(0.8, 1.0), rng.uniform(0.6, 1.0)])
        if rng.random() < 0.3:
            tint = tint[::-1]  # cool white
        radiance = power / (4 * sx * sz) * tint / tint.max()
        b.add(f"light_{i}", "rectangle", {"type": "diffuse", "base_color": [0.0, 0.0, 0.0]},
              {"translate": [_r(x), _r(height - 0.005), _r(z)], "rotate": [{"axis": [1, 0, 0], "angle": 90}],
               "scale": [_r(sx), _r(sz), 1]}, emitter=_rgb(radiance))


def _objects(b: _Builder, hx: float, hz: float, height: float) -> None:
    rng = b.rng
    n = int(rng.integers(2, 7))
    kinds = [str(rng.choice(["principled_metal", "conductor"])), str(rng.choice(["principled", "diffuse_textured"]))]
    kinds += [str(k) for k in rng.choice(OBJECT_MATERIALS, n - 2, p=OBJECT_WEIGHTS)]
    placed: list[tuple[float, float, float]] = []  # floor footprints (x, z, radius)
    free_walls = ["wall_back", "wall_front", "wall_left", "wall_right"]
    for i, kind in enumerate(kinds):
        shape = str(rng.choice(["sphere", "cube", "rectangle"], p=[0.35, 0.4, 0.25]))
        if shape == "rectangle" and not free_walls:
            shape = "cube"
        material = b.material(kind)
        name = f"{shape}_{i}"
        if shape == "rectangle":  # a panel (mirror, poster, metal plate) hung on a wall, facing the room
            wall = free_walls.pop(int(rng.integers(len(free_walls))))
            w, h = rng.uniform(0.25, 0.7), rng.uniform(0.25, 0.6)
            half = hx if wall in ("wall_back", "wall_front") else hz
            along = rng.uniform(-(half - w - 0.1), half - w - 0.1)
            y = rng.uniform(h + 0.3, height - h - 0.2)
            pos, angle = {"wall_back": ([along, y, -hz + 0.01], 0), "wall_front": ([along, y, hz - 0.01], 180),
                          "wall_left": ([-hx + 0.01, y, along], 90), "wall_right": ([hx - 0.01, y, along], -90)}[wall]
            b.add(name, "rectangle", material, {"translate": _rgb(pos), "rotate": [{"axis": [0, 1, 0], "angle": angle}],
                                                "scale": [_r(w), _r(h), 1]})
            continue
        for _ in range(100):  # a free spot on the floor
            if shape == "sphere":
                r = rng.uniform(0.15, MAX_OBJECT_TOP / 2)
                size, footprint = [r, r, r], r
            else:
                size = [rng.uniform(0.15, 0.45), rng.uniform(0.15, MAX_OBJECT_TOP / 2), rng.uniform(0.15, 0.45)]
                footprint = math.hypot(size[0], size[2])
            x = rng.uniform(-(hx - footprint - 0.1), hx - footprint - 0.1)
            z = rng.uniform(-(hz - footprint - 0.1), hz - footprint - 0.1)
            if all(math.hypot(x - px, z - pz) > footprint + pr + 0.05 for px, pz, pr in placed):
                break
        else:
            continue  # the floor is full: drop this object
        placed.append((x, z, footprint))
        tr = {"translate": _rgb([x, size[1], z]), "scale": _rgb(size)}
        if shape == "cube":
            tr["rotate"] = [{"axis": [0, 1, 0], "angle": _r(rng.uniform(0, 90))}]
        b.add(name, shape, material, tr)


def random_scene_config(seed: int, resolution: tuple[int, int] = (64, 64), views: int = 8, spp: int = 64,
                        denoise: bool = True) -> dict:
    """A random room as a ``synth:`` config section (plain dict, YAML / JSON friendly). ``resolution`` is
    (W, H); all ``views`` cameras are in the train split (no test views). Deterministic per ``seed``.
    ``denoise``: OIDN on the rendered layers (``render.denoise_view``), so that the buffers a network learns
    hold no Monte Carlo noise (caustic fireflies in the diffuse layer, which no predictor can reproduce)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if views < 1 or spp < 1:
        raise ValueError(f"views and spp must be >= 1, got views={views}, spp={spp}")
    rng = np.random.default_rng(seed)
    hx, hz = rng.uniform(1.6, 3.0, 2)
    height = rng.uniform(2.3, 3.2)
    b = _Builder(rng)
    _room(b, hx, hz, height)
    _lights(b, hx, hz, height)
    _objects(b, hx, hz, height)
    radius = rng.uniform(0.5, 1.0) * (min(hx, hz) - 0.6)
    heights = sorted(rng.uniform(MIN_CAMERA_HEIGHT, min(2.0, height - 0.3), 2))
    start = rng.uniform(0, 360)
    target = [rng.uniform(-0.3, 0.3), rng.uniform(0.2, 0.6), rng.uniform(-0.3, 0.3)]
    train = {"type": "orbit", "count": int(views), "fov_y": _r(rng.uniform(50, 75)), "target": _rgb(target),
             "radius": _r(radius), "height": _rgb(heights), "azimuth": [_r(start), _r(start + 360)]}
    return {
        "seed": int(seed),
        "resolution": [int(resolution[0]), int(resolution[1])],
        "spp": int(spp),
        "max_depth": 4,
        "denoise": bool(denoise),
        "textures": b.textures,
        "objects": b.objects,
        "cameras": {"train": train, "test": {"type": "orbit", "count": 0}},
    }


def mirror_like(material: dict) -> bool:
    """A smooth metal (conductor or metallic principled, roughness < 0.15): its reflection is sharp."""
    metal = material.get("type") == "conductor" or material.get("metallic") == 1.0
    return metal and float(material.get("roughness", 0.0)) < 0.15


def probe_worthy(config: dict) -> bool:
    """A room worth a held-out probe: at least two mirror-like objects and one glossy dielectric (principled,
    roughness < 0.2: the floor counts), so that mirrors, other shiny things and a glossy surface share the views."""
    materials = [o["material"] for o in config["objects"]]
    glossy = [m for m in materials if m.get("type") == "principled" and m.get("metallic") == 0.0
              and float(m.get("roughness", 1.0)) < 0.2]
    return sum(mirror_like(m) for m in materials) >= 2 and len(glossy) >= 1


def probe_scene(seed: int, resolution: tuple[int, int] = (128, 96), views: int = 20, spp: int = 256) -> dict:
    """A held-out probe: the random room of ``seed`` (``random_scene_config``, the buffer network's training rooms)
    as a scene document (``configs/scenes/*.yaml``: scene, kind, presets, synth) with three test views that look
    where the training orbit does not: halfway between its azimuths, 1.35x its radius (inside the walls, at least
    0.3 m from them) and at MIN_CAMERA_HEIGHT, below every training camera, so that they see sides of the objects
    the orbit looks down on. Nobody tunes to these rooms (README, "Held-out probes")."""
    synth = random_scene_config(seed, resolution=resolution, views=views, spp=spp)
    train = synth["cameras"]["train"]
    floor = next(o for o in synth["objects"] if o["name"] == "floor")
    hx, hz = floor["transform"]["scale"][:2]  # the room's half extents
    tx, tz = train["target"][0], train["target"][2]
    reach = min(hx - abs(tx), hz - abs(tz)) - 0.3  # the orbit's centre is the target, off the room's centre
    step = 360.0 / train["count"]
    start = train["azimuth"][0] + step / 2
    synth["cameras"]["test"] = {
        "type": "orbit", "count": 3, "fov_y": train["fov_y"], "target": train["target"],
        "radius": _r(min(1.35 * train["radius"], reach)),
        "height": [MIN_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT], "azimuth": [_r(start), _r(start + 360.0)],
    }
    return {"scene": f"probe_{seed}", "kind": "synthetic", "presets": ["fast"], "synth": synth}


def _forward(position, target) -> np.ndarray:
    d = np.asarray(target, float) - np.asarray(position, float)
    return d / np.linalg.norm(d)


def _box_corners(obj: dict) -> np.ndarray:
    """[8, 3] corners of a floor object's (sphere or y-rotated cube, unit shapes scaled) world bounding box."""
    tr = obj["transform"]
    centre, half = np.asarray(tr["translate"], float), np.asarray(tr["scale"], float)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    local = signs * half
    for rot in tr.get("rotate", []):  # cubes turn about y only
        a = math.radians(rot["angle"])
        c, s = math.cos(a), math.sin(a)
        local = local @ np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
    return centre + local


def _shiny(material: dict) -> bool:
    """A metal smooth enough to reflect the room (roughness < 0.3)."""
    metal = material.get("type") == "conductor" or material.get("metallic") == 1.0
    return metal and float(material.get("roughness", 0.0)) < 0.3


def _without_panels(objects: list[dict], axis: int, at: float, tol: float) -> list[dict]:
    """``objects`` less the panels (``_objects``' rectangles hung on a wall) whose centre's coordinate ``axis`` is
    within ``tol`` of ``at``: those on one wall."""
    return [o for o in objects if not (
        o["shape"] == "rectangle" and o["name"] not in ("floor", "ceiling") and not o["name"].startswith(("wall_", "light_"))
        and abs(o["transform"]["translate"][axis] - at) < tol)]


def mirror_probe_scene(seed: int, resolution: tuple[int, int] = (128, 96), views: int = 20, spp: int = 256) -> dict:
    """A held-out probe of what the cameras see only in a planar mirror: the random room of ``seed``
    (``random_scene_config``: its walls, lights and objects unchanged) with a wall mirror (a perfect conductor
    over most of the back wall, the panels that hung there removed), ``views`` training cameras standing in the
    room's front half and looking at the mirror, and three test cameras near the mirror turned round towards
    what stands behind every training camera (the floor objects no training camera faces: ``evaluate.regions``
    ``hidden_<name>``, their boxes + 5 cm). Whether the room is worth it: ``mirror_probe_worthy``."""
    synth = random_scene_config(seed, resolution=resolution, views=views, spp=spp)
    rng = np.random.default_rng([seed, 2026])  # its own stream: the room is random_scene_config(seed)'s
    floor = next(o for o in synth["objects"] if o["name"] == "floor")
    ceiling = next(o for o in synth["objects"] if o["name"] == "ceiling")
    hx, hz = floor["transform"]["scale"][:2]
    height = ceiling["transform"]["translate"][1]
    back = -hz + 0.01  # where random_scene_config hangs the back wall's panels
    synth["objects"] = _without_panels(synth["objects"], 2, back, 1e-3)
    mw, mh = min(hx - 0.3, 1.6), min((height - 0.5) / 2, 1.0)
    my = 0.3 + mh
    synth["objects"].append({"name": "mirror", "shape": "rectangle",
                             "material": {"type": "conductor", "roughness": 0.0, "specular_reflectance": [0.95, 0.95, 0.95]},
                             "transform": {"translate": [0.0, _r(my), _r(-hz + 0.02)], "scale": [_r(mw), _r(mh), 1]}})
    z0 = rng.uniform(0.0, 0.3) * hz
    top = min(2.0, height - 0.3)
    train = []
    for i, x in enumerate(np.linspace(-0.45 * hx, 0.45 * hx, views)):
        pos = [x + rng.uniform(-0.05, 0.05), MIN_CAMERA_HEIGHT + (top - MIN_CAMERA_HEIGHT) * (i % 3) / 2,
               z0 + 0.35 * (i % 2)]
        target = [0.6 * x + rng.uniform(-0.2, 0.2), my - 0.1 + rng.uniform(-0.15, 0.15), -hz]
        train.append({"position": _rgb(pos), "target": _rgb(target)})
    fov = _r(rng.uniform(50, 65))
    synth["cameras"]["train"] = {"type": "list", "count": views, "fov_y": fov, "views": train}
    hidden = [o for o in synth["objects"] if o["shape"] in ("sphere", "cube") and _seen_by(o, train) == 0]
    if hidden:
        aim = np.mean([o["transform"]["translate"] for o in hidden], axis=0)
        aim[1] = 0.4
    else:
        aim = np.array([0.0, 0.4, hz])
    synth["cameras"]["test"] = {"type": "list", "count": 3, "fov_y": fov, "views": [
        {"position": _rgb([x, y, -hz + 0.7]), "target": _rgb(aim)}
        for x, y in ((-0.4 * hx, 1.3), (0.0, 1.5), (0.4 * hx, 1.35))]}
    regions = {}
    for o in hidden:
        corners = _box_corners(o)
        regions[f"hidden_{o['name']}"] = {"min": _rgb(corners.min(0) - 0.05), "max": _rgb(corners.max(0) + 0.05)}
    return {"scene": f"probe_mirror_{seed}", "kind": "synthetic", "presets": ["fast"], "synth": synth,
            "evaluate": {"regions": regions}}


def _seen_by(obj: dict, cameras: list[dict]) -> int:
    """How many of ``cameras`` ({position, target}) have a corner of ``obj``'s box in front of their image plane
    (0: none can see it directly, whatever its field of view)."""
    corners = _box_corners(obj)
    return sum(bool(((corners - c["position"]) @ _forward(c["position"], c["target"]) > 0.05).any()) for c in cameras)


def mirror_probe_worthy(doc: dict) -> bool:
    """A mirror probe worth running: at least one floor object behind every training camera (seen only in the
    mirror) and, among the objects the cameras do face, at least one shiny metal (roughness < 0.3), so that
    the mirror shares the views with another shiny thing."""
    synth = doc["synth"]
    train = synth["cameras"]["train"]["views"]
    floor_objects = [o for o in synth["objects"] if o["shape"] in ("sphere", "cube")]
    seen = [o for o in floor_objects if _seen_by(o, train) > 0]
    return len(seen) < len(floor_objects) and any(_shiny(o["material"]) for o in seen)


WALLS = {  # random_scene_config's walls: name -> (axis across it, sign of the wall's side, rotation about y)
    "wall_back": (2, -1, 0), "wall_front": (2, 1, 180), "wall_left": (0, -1, 90), "wall_right": (0, 1, -90)}


def lights_probe_scene(seed: int, resolution: tuple[int, int] = (128, 96), views: int = 20, spp: int = 256) -> dict:
    """A held-out probe of lights in view beside glossy metal: ``probe_scene(seed)`` (its room, orbit and test
    views) with a window (an emitter, radiance 6-14, 0.6-1.2 x 0.5-0.9 m) on the wall the most training cameras
    look at (its panels removed) and one floor object turned brushed metal (metallic principled, roughness
    0.15-0.28: its highlights blur the lights it reflects, as a fridge or a pot does). Real interiors show
    lamps and windows beside shiny things; the mechanisms that place lights from reflections must not misplace
    the ones the cameras see (README, fifty-seventh session). Whether the room is worth it:
    ``lights_probe_worthy``."""
    from .cameras import path_poses
    from .spec import parse_camera_path

    doc = probe_scene(seed, resolution=resolution, views=views, spp=spp)
    synth = doc["synth"]
    rng = np.random.default_rng([seed, 2057])  # its own stream: the room is random_scene_config(seed)'s
    floor = next(o for o in synth["objects"] if o["name"] == "floor")
    ceiling = next(o for o in synth["objects"] if o["name"] == "ceiling")
    hx, hz = floor["transform"]["scale"][:2]
    height = ceiling["transform"]["translate"][1]
    poses = path_poses(parse_camera_path(synth["cameras"]["train"], "train"))
    looks = {name: sum(float(-p[axis, 2]) * side > 0.5 for p in poses) for name, (axis, side, _) in WALLS.items()}
    wall = max(WALLS, key=lambda n: (looks[n], n))
    axis, side, angle = WALLS[wall]
    at = (hz if axis == 2 else hx) * side
    synth["objects"] = _without_panels(synth["objects"], axis, at, 0.02)
    half = hx if axis == 2 else hz  # the wall's half width
    w, h = rng.uniform(0.3, 0.6), rng.uniform(0.25, 0.45)
    along = rng.uniform(-0.5, 0.5) * (half - w - 0.2)
    y = rng.uniform(h + 0.5, max(h + 0.5, min(1.7, height - h - 0.3)))  # low: the orbit looks down at the room
    centre = [along, y, at - side * 0.005] if axis == 2 else [at - side * 0.005, y, along]
    level = rng.uniform(6.0, 14.0)
    tint = np.array([rng.uniform(0.8, 0.95), rng.uniform(0.9, 1.0), 1.0])  # daylight, a little cool
    synth["objects"].append({"name": "window", "shape": "rectangle",
                             "material": {"type": "diffuse", "base_color": [0.0, 0.0, 0.0]},
                             "transform": {"translate": _rgb(centre), "rotate": [{"axis": [0, 1, 0], "angle": angle}],
                                           "scale": [_r(w), _r(h), 1]},
                             "emitter": {"radiance": _rgb(level * tint)}})
    solid = [o for o in synth["objects"] if o["shape"] in ("sphere", "cube")]
    if solid:
        brushed = max(solid, key=lambda o: float(np.prod(o["transform"]["scale"])))
        brushed["material"] = {"type": "principled", "base_color": _rgb(rng.uniform(0.75, 0.95, 3)),
                               "roughness": _r(rng.uniform(0.15, 0.28)), "metallic": 1.0, "specular": 0.5}
    doc["scene"] = f"probe_lights_{seed}"
    return doc


def lights_probe_worthy(doc: dict) -> bool:
    """A lights probe worth running: its window's centre inside the middle 80 % (each way) of at least three
    training cameras' frames (seen directly, not only at an edge), and a brushed-metal object."""
    from .cameras import path_poses
    from .spec import parse_camera_path

    synth = doc["synth"]
    window = next((o for o in synth["objects"] if o["name"] == "window"), None)
    if window is None or not any(o["material"].get("metallic") == 1.0 and 0.1 < o["material"].get("roughness", 0) < 0.3
                                 for o in synth["objects"] if o["shape"] in ("sphere", "cube")):
        return False
    c = np.asarray(window["transform"]["translate"], float)
    width, height = synth["resolution"]
    ty = math.tan(math.radians(synth["cameras"]["train"]["fov_y"]) / 2)
    tx = ty * width / height
    seen = 0
    for p in path_poses(parse_camera_path(synth["cameras"]["train"], "train")):
        x, y, z = (c - p[:3, 3]) @ p[:3, :3]  # camera frame, looking down -z
        seen += bool(z < 0 and abs(x / -z) < 0.8 * tx and abs(y / -z) < 0.8 * ty)
    return seen >= 3
