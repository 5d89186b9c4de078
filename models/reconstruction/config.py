"""Reconstruction settings (the ``reconstruct`` config section); defaults are the reference's (REFERENCE.md).

One dataclass tree, a doc per field: the schema of the section (``workflow/schemas/reconstruct.schema.yaml``) is
generated from it (``models/settings.py``). Adding an option is one field here (and the regenerated schema).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from models.pathtrace.brdf import DIFFUSE_LOBES, FRESNEL_MODES
from models.pathtrace.paths import BACK_NORMALS, REFLECTION_ORIGINS, PathConfig
from models.reconstruction.hole_fill import HOLE_FILL_MODES
from models.settings import from_dict, setting
from models.tracer.config import TracerConfig

_PATH = PathConfig()


@dataclass
class LossWeights:
    """Loss weights (paper Eq. 4-7)."""

    diffuse: float = setting(5.0, "L1 on the first segment's diffuse layer", minimum=0)
    specular: float = setting(3.0, "L1 on the path-traced specular estimate (after warm-up)", minimum=0)
    depth: float = setting(2.5, "L1 on expected depth (distance along the ray), in units of the scene's size / 6 "
                           "(metres in a 4 x 2.5 x 4 m room, whose diagonal is ~6 m; scale-free)", minimum=0)
    normal: float = setting(2.5, "L1 on the accumulated (unnormalised) normal", minimum=0)
    roughness: float = setting(1.0, "L1 on blended roughness", minimum=0)
    f0: float = setting(1.0, "L1 on blended F0", minimum=0)
    stereo_depth: float = setting(0.0, "after warm-up, on reflected rays of the planar mirrors where mirror stereo "
                                  "matched a depth by its own texture (models/reconstruction/mirror_stereo.py): L1 "
                                  "on how far the ray's "
                                  "expected depth (given it ends) falls in front of that depth, less what the sweep "
                                  "cannot tell apart and stereo_depth_margin of it; units as depth. What the "
                                  "cameras see only in a mirror is otherwise constrained by colour alone, and "
                                  "half-transparent Gaussians grow into the air in front of it. Off by "
                                  "default: at 2.5 six fast pairs (zoo_mirror_metal, zoo_mirror_only, seeds 0-2, "
                                  "fiftieth session) moved the final -0.69 to +1.70 dB, mean +0.15, the seed-to-seed "
                                  "spread of the view behind the cameras; 0 = off", minimum=0)
    stereo_depth_rays: int = setting(1024, "with stereo_depth: reflected rays drawn per step", minimum=1)
    stereo_depth_margin: float = setting(0.2, "with stereo_depth: the loss stops this share of the free distance "
                                         "short of it (at 0.05 a grazing floor's Gaussians, spread along the ray in "
                                         "front of its depth, were pushed out: holes in zoo_mirror_only, -1.5 dB)",
                                         minimum=0, maximum=1)
    prior_smooth: float = setting(2.0, "L1 between each plane-fill Gaussian's diffuse colour and the mean of its 8 "
                                  "nearest fill neighbours' on its own surface (averaged over the fill; not in the "
                                  "paper). What no training view sees is trained by reflections alone, one noisy "
                                  "sample per ray: "
                                  "left free, each fill Gaussian took its own colour (zoo_lamps' unseen ceiling: "
                                  "colour std 0.03 -> 0.15 over training, a confetti ceiling); 0 = off", minimum=0)


@dataclass
class LearningRates:
    """Adam learning rates per parameter group."""

    position_init: float = setting(1.6e-4, "x scene extent, decays exponentially to position_final", minimum=0)
    position_final: float = setting(1.6e-6, "x scene extent", minimum=0)
    normal: float = setting(0.0025, minimum=0)
    roughness: float = setting(0.0025, minimum=0)
    f0: float = setting(0.0025, minimum=0)
    diffuse: float = setting(0.005, minimum=0)
    opacity: float = setting(0.025, minimum=0)
    scale: float = setting(0.005, minimum=0)
    rotation: float = setting(0.001, minimum=0)


# path settings that only a trained model's renders take from the config: training keeps these values (every
# reflection a fixed offset past its surface, a normal met from behind flipped), and Trainer.settings writes the
# config's into model.yaml (reconstruct.origin_grazing, reconstruct.back_normal)
RENDER_ONLY_PATH = {"origin_grazing": 1.0, "back_normal": "flip"}


@dataclass
class ReconstructConfig:
    """Reconstruction of one Gaussian scene with path-traced reflections."""

    iterations: int = setting(8000, "optimisation steps", minimum=1)
    warmup: int = setting(750, "steps with primary rays only; then reflections (and far field) on", minimum=0)
    rays_per_step: int = setting(0, "rays per step drawn from all training pixels; 0 = one whole view per step",
                                 minimum=0)
    max_path_length: int = setting(_PATH.max_path_length, "path segments (1 = no reflections); stored with the "
                                   "model, renders use it", minimum=1, maximum=16)
    max_path_length_limit: int = setting(8, "the longest path the path-length decision may choose where mirror-like "
                                         "surfaces face each other (metal walls, a mirror facing a chrome "
                                         "object): when reflections turn on, halfway and at the end, reflections "
                                         "leaving mirror-like training pixels in random directions are traced; "
                                         "while more than path_tail_rays of them still carry more than "
                                         "path_tail_throughput after the path length, it grows (up to this; "
                                         "stored with the model); <= max_path_length: never",
                                         minimum=1, maximum=16)
    path_tail_throughput: float = setting(0.2, "see max_path_length_limit: the throughput (max over RGB) a path still "
                                          "carries that counts it as cut short", exclusiveMinimum=0, maximum=1)
    path_tail_rays: float = setting(0.05, "see max_path_length_limit: the fraction of those reflections that may be "
                                    "cut short", minimum=0, maximum=1)
    sampler: str = setting(_PATH.sampler, "reflection sampling: vndf | ndf (reference); stored with the model",
                           enum=["vndf", "ndf"])
    fresnel: str = setting(_PATH.fresnel, "the Fresnel term: schlick_f90 (Schlick's with F90 = min(1, 50 mean "
                           "F0): a surface with F0 = 0, a matte one, reflects nothing, as in the capture) | schlick "
                           "(F90 = 1, the paper's: F0 = 0 still reflects (1 - cos)^5) | dielectric (the exact "
                           "Fresnel of a dielectric, eta from F0, up to F0 0.08, schlick_f90 from 0.2, blended "
                           "between: Schlick's is 20 % low at 60 degrees for F0 0.04); stored with the model",
                           enum=list(FRESNEL_MODES))
    reflection_origin: str = setting(_PATH.reflection_origin, "where a reflection starts along the ray that met "
                                     "the surface: front (the mean depth of the hits blended while the "
                                     "transmittance is >= 0.5) | expected (the expected depth, the paper's: from "
                                     "an angle no training camera saw it from, it lies inside a curved surface's "
                                     "Gaussians, which then shadow its reflections: zoo_spheres, README); stored "
                                     "with the model", enum=list(REFLECTION_ORIGINS))
    diffuse_lobe: str = setting(_PATH.diffuse_lobe, "how a Gaussian's diffuse radiance depends on the viewing "
                                "angle: disney (as Mitsuba's principled diffuse under uniform light, on surfaces "
                                "with a specular lobe, F0 > 0: 0.6-0.75x towards grazing views on a smooth one, up "
                                "to 1.46x on a rough one, as the capture's diffuse layer of such materials) | "
                                "lambert (it does not, the paper's); stored with the model",
                                enum=list(DIFFUSE_LOBES))
    hole_fill: str = setting("auto", "whether the model this run writes renders with the hole fill (a ray's "
                             "blended diffuse divided by its opacity: what is left of its transmittance takes the "
                             "colour it blended, models/pathtrace/paths.py): auto (on where the trained model's "
                             "training views are opaque, at most 1 % of their pixels keeping a transmittance above "
                             "0.5: a closed scene; off where they look past it, an object on a black background) | "
                             "on | off (background 0, the paper's). Training is the same either way; the decision "
                             "is in the decisions log and in model.yaml (path.hole_fill)",
                             enum=list(HOLE_FILL_MODES))
    loss: LossWeights = setting(default_factory=LossWeights, doc="loss weights")
    lr: LearningRates = setting(default_factory=LearningRates, doc="learning rates")
    tracer: TracerConfig = setting(default_factory=TracerConfig, doc="ray tracer settings (kernel_p, "
                                   "transmittance_threshold, ...); stored with the model, so every consumer "
                                   "renders it the way it was trained")
    adam_eps: float = setting(1e-15, "Adam epsilon", exclusiveMinimum=0)
    prune_every: int = setting(125, "pruning period (steps); 0 = never", minimum=0)
    max_thickness: float = setting(0.01, "a Gaussian's thinnest axis (its scale) is clamped to at most this x the "
                                   "scene's size after every step (fixed ones, and far-field ones outside the "
                                   "captured room's box, keep theirs; with thickness_reflected_only, the default, "
                                   "only the mirror fills' Gaussians are held); 0 = off. Surfaces are thin: a "
                                   "Gaussian that only reflections train (what mirrors show behind the cameras) "
                                   "otherwise grows into a blob tens of centimetres thick that a test view standing "
                                   "there looks through (README)", minimum=0)
    thickness_reflected_only: bool = setting(True, "max_thickness clamps only the Gaussians the mirror fills "
                                             "placed (mirror stereo, reflection fill: what the cameras see only in "
                                             "mirrors, which no view pins to a thin surface); the rest of the room "
                                             "keeps its scales. false: every Gaussian in the room (zoo_mirror_only "
                                             "seed 0: 27.64 -> 25.87, a sheet in front of a test view; README)")
    prune_from: int = setting(1250, "first step that prunes", minimum=0)
    prune_min_weight: float = setting(0.1, "keep Gaussians whose blending weight summed over a view, averaged over "
                                      "views, is >= this at the reference's 768-pixel image height (scaled by "
                                      "(H / 768)^2 at height H)", minimum=0)
    prune_hidden: bool = setting(True, "a pruning step also removes the initialisation's Gaussians (none a fill "
                                 "placed) that every training camera's view of the room hides: outside its frame, "
                                 "or behind the surface its depth buffer shows there by more than "
                                 "HIDDEN_SLACK of that depth plus HIDDEN_REACH x the Gaussian's largest scale. "
                                 "Placed on what the cameras saw, such a Gaussian has moved where only "
                                 "reflections train it, and nothing holds its depth (probe_mirror_213: a dark "
                                 "disc 11 cm over the floor behind a copper sphere, seen only in the wall mirror, "
                                 "covered the sphere in the test views; README). What the cameras see only in "
                                 "mirrors is the mirror fills' (their Gaussians, the far field's, the emitters' "
                                 "and the priors' are not tested)")
    prune_views: int = setting(8, "views traced to measure blending weights at a pruning step: the next block of a "
                               "random cycle through the training views; a Gaussian goes once the blocks have "
                               "covered them all (Trainer.prune)", minimum=1)
    far_field: str = setting("auto", "auto (only if reflections can see past the capture) | on | off",
                             enum=["auto", "on", "off"])
    far_field_count: int = setting(75000, "far-field Gaussians added at the end of warm-up", minimum=0)
    far_field_hidden: float = setting(0.05, "far-field Gaussians that no training camera sees past the captured room "
                                      "(the warmed-up scene and the fills let less than this through on the "
                                      "segment from every camera to them) are not added: behind a closed wall "
                                      "they train on reflections that slip through it and show through any thin "
                                      "spot (zoo_lshape test_002: one of radiance 8.5 behind the wall round the "
                                      "window made 66 % of the view's bright error); 0 = keep all",
                                      minimum=0, maximum=1)
    far_field_margin: float = setting(0.0, "after every step each far-field Gaussian is shrunk (never moved) until "
                                      "this many of its standard deviations, along the axis that best separates it "
                                      "from the captured room's box, stay outside that box: the shell the "
                                      "reflections see past the capture, not a veil inside the room (zoo_mirror_only: "
                                      "far-field Gaussians grown to 2.6 m reached through the wall seen only in the "
                                      "mirror and put F0 0.04 on the test views' matte wall); 0 = off", minimum=0)
    far_field_escape: float = setting(0.01, "auto: on when more mirror-like reflections than this miss the init",
                                      minimum=0, maximum=1)
    reflection_fill_count: int = setting(0, "with the far field: Gaussians along open mirror reflections (0 = off)",
                                         minimum=0)
    mirror_stereo_count: int = setting(8000, "with the far field: Gaussians placed by stereo on planar mirrors "
                                       "(0 = off)", minimum=0)
    mirror_stereo_opacity: float = setting(0.3, "mirror stereo: the opacity its Gaussians start at (they train). "
                                           "0.9 measured: zoo_mirror_metal 30.02 -> 30.01 at seed 0; "
                                           "zoo_mirror_only 28.78, against 29.02 of an older code's model "
                                           "(README, fortieth session)",
                                           minimum=0.01, maximum=0.99)
    mirror_stereo_min_share: float = setting(0.3, "mirror stereo: a depth is a candidate only where at least this "
                                             "share of the other views' mirrors (and at least 3) see it: 6 of 19 on a "
                                             "20-view room, however many mirror planes each view holds (3 placed a fifth more stereo Gaussians on "
                                             "zoo_mirror_metal and more haze in its view from behind the cameras; "
                                             "models/reconstruction/mirror_stereo.py)", minimum=0, maximum=1)
    plane_fill_count: int = setting(20000, "Gaussians (at most) on the unseen parts of the planes that bound the "
                                    "room (walls, floor, ceiling found in the depth + normal buffers), added before "
                                    "warm-up, geometry frozen, never pruned for want of blending weight "
                                    "(plane_fill.py; zoo_lamps tonemapped final 26.0 -> 29.9); 0 = off (the paper)",
                                    minimum=0)
    plane_fill_relight: bool = setting(True, "at the end of warm-up (when the lights the cameras see only in "
                                       "mirrors are placed) the plane fill's colour becomes its plane's albedo (seen "
                                       "radiance / traced irradiance) x the irradiance the model sends where each of "
                                       "its Gaussians is, not the nearest seen radiance (plane_fill.relight_plane_fill; "
                                       "zoo_lamps 31.54 -> 33.05 and 31.50 -> 32.90 at two seeds; README)")
    plane_fill_relight_at: float = setting(0.0, "when the plane fill is relit: this fraction of the way from the end "
                                           "of warm-up to the last step (0 = when reflections turn on)",
                                           minimum=0, maximum=1)
    sphere_fill: bool = setting(False, "Gaussians on the unseen far sides of round shiny objects: a sphere fitted "
                                "to each piece of shiny pixel points that is one (residual, normals, arc), the rest "
                                "of it covered with Gaussians held fixed (nothing of theirs trains), never pruned "
                                "for want of weight (sphere_fill.py). Off: zoo_spheres' far-side view gains 2.7 dB "
                                "(normals 66 -> 8 degrees off), the zoo's rooms move within the draws (README)")
    jitter: bool = setting(False, "training rays through a uniform random point of their pixel, not its centre "
                           "(the ground truth's pixel is the mean over its area); the fills and the pruning keep the "
                           "centres (batches.py). Off: final tonemapped -0.17 to -0.71 dB in the four zoo rooms "
                           "measured (README)")
    sphere_snap: bool = setting(True, "after the last step: each round shiny object the training views show (a "
                                "sphere fitted as for sphere_fill) replaced by a fine lattice of discs on the sphere "
                                "with the material the capture's buffers give it, held fixed; a fit the training "
                                "views see through is left as trained (sphere_snap.py). zoo_spheres final "
                                "tonemapped 24.8 -> 28.5, the demo 36.5 -> 36.8 (README)")
    stereo_on_planes: bool = setting(True, "mirror-stereo Gaussians on one of the room's planes become plane-fill "
                                     "surfels (on the plane, geometry frozen, the plane's F0 and roughness, the colour "
                                     "the mirrors show) instead of free matte blobs (plane_fill.stereo_on_planes)")
    stereo_plane_tol: float = setting(1.0, "a mirror-stereo Gaussian is on one of the room's planes (stereo_on_planes) "
                                      "within this x the plane tolerance (1 % of the scene's size); the stereo's "
                                      "depths of a wall seen only in a mirror scatter tens of centimetres, and those "
                                      "in front of it stay free blobs, a veil where a test view stands (README)",
                                      minimum=0)
    stereo_plane_slack: float = setting(0.1, "> 0: a mirror-stereo Gaussian also joins a room plane "
                                        "(stereo_on_planes) where its reflected ray crosses the plane at a depth "
                                        "whose sweep cost is within this fraction of the best depth's (flat walls "
                                        "seen only in mirrors match over tens of centimetres; textured objects "
                                        "near a wall do not); 0 = off. With max_thickness on the mirror fills: "
                                        "zoo_mirror_metal 28.14 -> 29.27, 28.26 -> 29.28 (README)", minimum=0)
    back_fill: bool = setting(True, "after the last step: a second layer behind thin surfaces whose backs no "
                              "training view saw but the views saw empty space behind (a table top's underside), "
                              "with the front's material lit by what the model sends that side (back_fill.py). "
                              "zoo_thin final tonemapped 27.7 -> 29.0 (README); the other zoo rooms unchanged")
    close_room: bool = setting(True, "with the far field and the plane fill: walls no training view looks at (behind "
                               "the cameras, a ceiling above every frame), placed at the end of warm-up where sharp "
                               "reflections, curved mirrors too, agree on them (room_closing.py); a side whose "
                               "reflections agree best far away stays open")
    close_behind_lights: bool = setting(True, "with close_room and the highlight fill: a side the sweep leaves open "
                                        "is closed one grid spacing behind the emitters the highlight fill put on "
                                        "it, when its box scale is a minimum inside its search (a light hangs on "
                                        "a wall or a ceiling), and the lights are found again, those beyond the "
                                        "new wall moved onto it (room_closing.close_behind_lights). Held-out "
                                        "probe_9164 (a flat ceiling seen only in mirror cubes) 28.52 -> 30.61, "
                                        "probe_9256 29.91 -> 29.78; no zoo room or the demo takes it (README)")
    close_room_refine: bool = setting(True, "room closing refines each wall's offset by a parabola fitted to a fine "
                                      "sweep round the coarse one's minimum (whose steps are 14 %: ~10 cm at a "
                                      "ceiling): zoo_spheres' ceiling 0.12 -> 0.05 m low, the demo's 0.11 -> 0.03. "
                                      "Alone it lost (demo -0.44 / -0.31 dB at seeds 0 / 1, zoo_spheres -0.09); "
                                      "with highlight_to_walls and highlight_max_growth 3 (defaults since the "
                                      "thirty-first session) demo +0.25 / +0.64, zoo_spheres +0.06 / +0.15; rooms "
                                      "where closing places no wall are untouched (README)")
    highlight_fill: bool = setting(True, "with the far field: emitters seen only in mirrors (reflection_fill.py)")
    highlight_on_fill: bool = setting(True, "highlight fill: a highlight reflection that ends on the plane fill "
                                      "or on a wall placed after warm-up (a light on an unseen part of the room's "
                                      "planes: a ceiling lamp behind the cameras) gets an emitter there. Alone "
                                      "it lost (zoo_mirror_only -0.5 to -0.9 dB, twenty-third session; "
                                      "zoo_corridor -0.16, fortieth); with highlight_on_fill_plane, "
                                      "highlight_growth_all and plane_hold (defaults since the forty-ninth "
                                      "session) fourteen zoo pairs (every room, seeds 0 / 1) +0.20 dB (corridor "
                                      "+1.23 / +0.86, mirror_metal -0.73 / +0.64, lshape +0.64 / +0.17), the "
                                      "demo -0.31 / 0.00 (README, forty-eighth and forty-ninth sessions)")
    highlight_on_fill_purity: float = setting(0.0, "with highlight_on_fill: a highlight ending on the plane fill "
                                              "gets its emitter only where at least this share of the reflections "
                                              "ending near it on the fill (3 % of the room's size) are highlights "
                                              "too, not dark ones (0: every one gets it)", minimum=0.0, maximum=1.0)
    highlight_skip_seen_lights: bool = setting(True, "highlight fill: a highlight whose pixel's footprint where "
                                               "its emitter would go (the reflection's length x the angle to "
                                               "its neighbouring pixels' reflections plus its glossy lobe, 2 "
                                               "roughness^2) holds a light the training views see directly "
                                               "(emission > 0) gets no emitter: that light has its own Gaussians "
                                               "(zoo_lshape's brushed fridge put emitters round its window, on the "
                                               "wall no training view sees: 29.49 / 29.99 -> 30.40 / 30.55 at seeds "
                                               "0 / 1; default since the fifty-seventh session, README)")
    highlight_on_fill_plane: bool = setting(True, "with highlight_on_fill: the emitters go where their rays "
                                            "cross the room's plane under the fill, not the fill's front (a few cm "
                                            "short of it, so 10-20 cm short along a grazing ray: zoo_mirror_metal's "
                                            "ceiling lamp got emitters up to 0.2 m past its rim)")
    highlight_to_walls: bool = setting(True, "highlight fill: an emitter the box sweep leaves at most two of its "
                                       "steps short of a wall room closing placed moves along its ray onto the "
                                       "wall (the sweep tells a lamp's distance to ~10 cm, the wall better: the "
                                       "demo's ceiling lamp, 2.49 m up, sat at 2.22-2.31 under a ceiling placed "
                                       "at 2.47). Without highlight_max_growth it lost (zoo_spheres -0.70 at seed "
                                       "0, README twenty-ninth session); with it and close_room_refine: demo +0.25 "
                                       "/ +0.64 dB at seeds 0 / 1, zoo_spheres +0.06 / +0.15 (README, thirtieth and "
                                       "thirty-first sessions)")
    highlight_max_growth: float = setting(3.0, "the highlight fill's emitters that highlight_to_walls moved onto a "
                                          "wall keep each scale within this many times the median size the fill "
                                          "gave its emitters (0: no limit). Trained free, they grew into sheets up "
                                          "to 0.9 m across under the demo's ceiling, over its lamp (its gold cube's "
                                          "test_002: 29.8-32.8 -> 35.0-35.7 dB). Emitters no wall took stay free: "
                                          "bounded, zoo_corridor's (placed by the sweep on the box's near edge, "
                                          "re-purposed by training) cost it 0.52 / 0.65 dB at seeds 0 / 1 "
                                          "(README, thirtieth and thirty-first sessions)", minimum=0.0)
    highlight_growth_all: bool = setting(True, "highlight_max_growth holds every emitter the highlight fill "
                                         "places, not only those highlight_to_walls moved onto a wall (an emitter "
                                         "left in mid-air in front of a wall, as zoo_corridor's behind its cameras, "
                                         "otherwise grows into a rod or a sheet; off: only the wall ones)")
    highlight_frozen: bool = setting(False, "the highlight fill's emitters keep the place and size they were given "
                                     "(the plane fill's priors' rule) and their matte material (the mirror fills' "
                                     "rule); colour and opacity train. Trained free, those off the light dimmed and "
                                     "grew into sheets up to 0.9 m across just under the ceiling, one over the "
                                     "demo's lamp (its gold cube's top then reflected 0.38 of the true specular). "
                                     "Off: frozen, the demo's specular lost 1.8 dB at seed 1 (the emitters no "
                                     "longer grow to tile the lamp) and zoo_spheres 0.5 dB final (README)")
    fill_anchor: float = setting(3.0, "> 0: mirror-stereo and reflection-fill Gaussians (what the cameras see only "
                                 "in mirrors) are surfels facing the views that placed them: along that direction "
                                 "they stay within this many of their initial sizes of where the fill put them and "
                                 "grow at most this factor (reflections alone pin down no depth: free, they drift "
                                 "and swell in the part of the room no camera sees); 0 = free. 3, the default "
                                 "since the fifty-second session (two seeds each, anchored vs free: "
                                 "zoo_mirror_metal 29.63 / 29.85 vs 28.74 / 30.01, its frosted_mirror edit "
                                 "+5.87 / +5.71 vs +0.14 / +1.74; zoo_mirror_only 28.52 / 28.49 vs 28.95 / "
                                 "28.90; mirror_book +0.22; rooms where mirror stereo places nothing, e.g. "
                                 "zoo_corridor and the probes, bit-identical; anchors.py, README)",
                                 minimum=0)
    plane_hold: bool = setting(True, "the initialisation's Gaussians that lie flat on a wall, the floor or the "
                               "ceiling (a bounding plane of the plane fill's) face it and stay on it: rotation "
                               "frozen, thin scale at most its initial one, the mean within plane_hold_depth x "
                               "the plane tolerance of where it was along the normal, free along the plane "
                               "(trained free, a few tilted and hung 0.2-0.3 m below zoo_corridor's ceiling, "
                               "over its lights; plane_fill.hold_on_planes). Alone over nine zoo / demo pairs "
                               "+0.07 dB, within the seed spread (forty-fourth session); with the highlight "
                               "on-fill settings the default since the forty-ninth (README, forty-eighth)")
    plane_hold_depth: float = setting(0.5, "with plane_hold: how far a held Gaussian's mean may move along its "
                                      "plane's normal, x the plane tolerance (1 % of the room's size)", minimum=0)
    fill_matte: bool = setting(True, "mirror-stereo and reflection-fill Gaussians keep the matte material they "
                               "were made with (no buffer sees it; trained by the reflections' colour alone they "
                               "turned shiny in the air: zoo_mirror_only)")
    fill_spread: float = setting(10.0, "with fill_anchor: how far (in initial sizes) and by what factor those "
                                 "surfels may move and grow along the surface, to cover it", minimum=1)
    radiance_clamp: float = setting(0.0, "clamp target radiance (diffuse/specular) to this; 0 = off (real scenes: "
                                    "5.0)", minimum=0)
    origin_offset: float = setting(0.0016, "reflection rays start this far past their surface point, along the "
                                   "reflected ray, as a fraction of the scene's size (the diagonal of the box "
                                   "holding 98 percent of the initial Gaussians: 1 cm in a 4 x 2.5 x 4 m room); the "
                                   "model stores the resulting length", exclusiveMinimum=0, maximum=0.1)
    origin_grazing: float = setting(_PATH.origin_grazing, "the reflection's start offset (origin_offset) is "
                                    "divided by max(|cos|, this), cos between the surface normal and the "
                                    "reflected ray: a grazing reflection crosses the surface's own Gaussians over "
                                    "their thickness / cos (a chrome ball seen from where no training camera "
                                    "stood showed a ring of self-shadowed reflections); 1 = a fixed offset. "
                                    "Renders only: training keeps a fixed offset (trained with 0.1 the zoo moved "
                                    "-0.73 to +0.93 dB, the facing metal walls worst; rendered with it, nothing "
                                    "lost: README); stored with the model", exclusiveMinimum=0, maximum=1)
    back_normal: str = setting(_PATH.back_normal, "the normal a reflection takes where a ray meets the BACK "
                               "of what was reconstructed (the blended normal faces away from it): mirror (n "
                               "mirrored across the plane normal to the ray: exactly a ball's far-side normal where "
                               "a test view looks through the side no training camera saw at the inside of the "
                               "seen half; zoo_spheres 24.49 -> 25.21 dB rendered, the other zoo rooms within 0.02 "
                               "on those models and zoo_corridor -0.10 on older ones, the demo unchanged) | flip (-n, "
                               "a thin sheet's other side: that inside reflects as a concave bowl). Renders only: "
                               "training flips (trained with mirror the zoo moved -0.12 to +0.46: README); stored "
                               "with the model (paths.back_normal_from_behind)",
                               enum=list(BACK_NORMALS))
    min_throughput: float = setting(0.01, "training only: a reflection path stops where its throughput (max over "
                                    "RGB) is below this; the bounce's value and its gradient are proportional to "
                                    "the throughput, so such a path carries at most this share of a mirror's "
                                    "gradient (demo: 35% of the first bounce's rays, 0.09% of its gradient weight). "
                                    "Renders trace every path (0 = off)", minimum=0, exclusiveMaximum=1)
    checkpoint_every: int = setting(1000, "steps between checkpoints (and at the end)", minimum=1)
    log_every: int = setting(25, "steps between metrics-log lines", minimum=1)
    seed: int = setting(0, "random seed (ray batches, far field, fills)")

    @classmethod
    def from_dict(cls, d: dict) -> "ReconstructConfig":
        moved = sorted({"kernel_p", "transmittance_threshold"} & set(d))
        if moved:
            raise ValueError(f"reconstruct.{moved[0]} is now reconstruct.tracer.{moved[0]} (tracer settings are "
                             "stored with the model)")
        if "threads" in d:
            raise ValueError("reconstruct.threads is now reconstruct.tracer.num_threads")
        return from_dict(cls, d, "reconstruct")

    def path(self, scene_size: float) -> PathConfig:
        """The path settings this model trains (and is rendered) with, in a scene of size ``scene_size`` (the
        diagonal of its initial geometry, models.reconstruction.trainer.scene_size): lengths are fractions of it,
        so a scene scaled by any factor trains the same. Training adds ``min_throughput`` (``training_path``).
        Training takes ``RENDER_ONLY_PATH``'s values (a fixed reflection offset, a normal met from behind flipped);
        the model it writes renders with this config's (Trainer.settings)."""
        return PathConfig(max_path_length=self.max_path_length, sampler=self.sampler, fresnel=self.fresnel,
                          origin_offset=self.origin_offset * scene_size, reflection_origin=self.reflection_origin,
                          diffuse_lobe=self.diffuse_lobe, **RENDER_ONLY_PATH)

    def training_path(self, scene_size: float) -> PathConfig:
        """``path`` with the training-only path cut-off (``min_throughput``)."""
        return replace(self.path(scene_size), min_throughput=self.min_throughput)
