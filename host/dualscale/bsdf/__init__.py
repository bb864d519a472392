"""Differentiable dielectric SVBSDF of Garces et al. 2023 (supplementary Section 5).

Pure tensor functions (float32/float64, any device) for each term, the Fong normal
parametrisation, the canonical maps, and :func:`evaluate` for a whole map under many lights.
"""

from .fresnel import fresnel_dielectric, fresnel_p, fresnel_s, fresnel_weighted
from .ggx import (ALPHA_MIN, ggx_alphas, ggx_d_aniso, ggx_d_iso, smith_g, smith_g1, smith_lambda,
                  smith_visibility)
from .mapping import disc_to_square, normal_from_square, square_from_normal, square_to_disc, tangent_frame
from .maps import (DEFAULT_IOR, DIFFUSE_MODELS, MAP_CHANNELS, MAP_NAMES, Components, MaterialMaps, ior_from_map,
                   map_from_ior, map_from_tangent_angle, tangent_angle_from_map, validate_maps)
from .model import evaluate, prepare
from .reference import evaluate_reference
from .terms import (chromaticity, diffuse, diffuse_base, diffuse_lambert, retro_reflection, schlick_weight,
                    specular_aniso, specular_iso, specular_tint, transmittance)

__all__ = [
    "ALPHA_MIN", "DEFAULT_IOR", "DIFFUSE_MODELS", "MAP_CHANNELS", "MAP_NAMES", "Components", "MaterialMaps",
    "chromaticity", "diffuse", "diffuse_base", "diffuse_lambert", "disc_to_square", "evaluate", "evaluate_reference",
    "fresnel_dielectric", "fresnel_p", "fresnel_s", "fresnel_weighted", "ggx_alphas", "ggx_d_aniso", "ggx_d_iso", "ior_from_map",
    "map_from_ior", "map_from_tangent_angle", "normal_from_square", "prepare", "retro_reflection",
    "schlick_weight", "smith_g", "smith_g1", "smith_lambda", "smith_visibility", "specular_aniso",
    "specular_iso", "specular_tint", "square_from_normal", "square_to_disc", "tangent_angle_from_map",
    "tangent_frame", "transmittance", "validate_maps",
]
