"""Specular path tracing math: Cook-Torrance GGX BRDF (`brdf`) and importance sampling
of the reflected direction (`sampling`). See the module docstrings for conventions.

`sampling` is imported lazily so that `python -m models.pathtrace.sampling` runs cleanly.
"""

from models.pathtrace.brdf import (
    DEFAULT_SMITH,
    MIN_ROUGHNESS,
    SMITH_MODELS,
    eval_specular,
    fresnel_schlick,
    ggx_d,
    reflect,
    roughness_to_alpha,
    smith_g,
    smith_g1,
    smith_visibility,
)

_SAMPLING = ("SpecularSample", "sample_vndf", "sample_ndf", "sample_specular", "pdf_vndf",
             "pdf_ndf", "tangent_frame", "compare_sampler_variance", "format_variance_table")

__all__ = [
    "DEFAULT_SMITH", "MIN_ROUGHNESS", "SMITH_MODELS", "eval_specular", "fresnel_schlick", "ggx_d",
    "reflect", "roughness_to_alpha", "smith_g", "smith_g1", "smith_visibility", *_SAMPLING,
]


def __getattr__(name):
    if name in _SAMPLING:
        from models.pathtrace import sampling

        return getattr(sampling, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
