"""Our SVBSDF maps (seed Sec. 5) in the exchange conventions of PBR material formats.

This module is the one place where our parameters become a format's parameters; the
per-format writers (:mod:`.gltf`, :mod:`.mtlx`, :mod:`.u3m`, :mod:`.exr`) only encode what it
returns.  ``docs/EXPORT.md`` tabulates, per format, what is exact, approximated and lost.

Conventions of the result (:class:`Exchange`), all arrays ``float32``, rows top to bottom
(row 0 = top of the image, as on disk), ``(H, W)`` or ``(H, W, C)``:

* **Tangent space** is the image: +x = image right (texture ``u``), +y = image up, +z out of
  the sample.  Normals are OpenGL-style (+Y up), the glTF, MaterialX and U3M convention;
  a DirectX (+Y down) map is ``normal * (1, -1, 1)``.
* ``base_color`` linear Rec.709 RGB in [0, 1] (formats store it sRGB-encoded or linear EXR).
* ``roughness`` is the *perceptual* roughness ``r`` of glTF, Standard Surface and OpenPBR,
  with GGX ``alpha = r^2`` -- the same convention as our ``sigma_r`` (Burley 2015), so an
  isotropic map is copied exactly.
* Anisotropy: ours is Burley's ``aspect = sqrt(1 - 0.9 a)``, ``alpha_t = r^2 / aspect``
  (along the tangent), ``alpha_b = r^2 aspect``; :func:`alphas` gives both and the format
  functions re-parametrise them exactly where the format can express them.
* ``tangent_angle`` [rad], the anisotropy direction CCW from +x (axial: modulo pi).
* ``ior`` per pixel (eta) and ``ior_scalar`` (its median) for formats with a single IOR.
* ``specular_color`` the F0 tint: ``chr(b) rho_s + 1 - rho_s`` (our specular tint).
* ``transmittance`` our diffuse transmittance ``t`` (linear RGB) and ``opacity`` (coverage).

Errors: ``ValueError`` for maps that fail :func:`dualscale.bsdf.validate_maps`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dualscale.bsdf import MaterialMaps, validate_maps
from dualscale.bsdf.maps import DEFAULT_IOR, ior_from_map


def _luminance_weights() -> np.ndarray:
    import colour

    return np.asarray(colour.RGB_COLOURSPACES["ITU-R BT.709"].matrix_RGB_to_XYZ[1], np.float64)


LUMINANCE = _luminance_weights()  # Y row of Rec.709 RGB -> XYZ (colour-science)


def _np(t) -> np.ndarray | None:
    return None if t is None else t.detach().cpu().numpy().astype(np.float32)


@dataclass
class Exchange:
    """Our maps in exchange conventions (see the module docstring); inactive parts are ``None``."""

    base_color: np.ndarray            # (H, W, 3) diffuse albedo b, linear
    roughness: np.ndarray             # (H, W) r = sigma_r, alpha = r^2 (isotropic part)
    anisotropy: np.ndarray | None     # (H, W) our a in [0, 1]
    tangent_angle: np.ndarray | None  # (H, W) rad CCW from image +x, in [0, pi)
    normal: np.ndarray | None         # (H, W, 3) unit, tangent space, OpenGL +Y up
    ior: np.ndarray | None            # (H, W) eta per pixel (None: ior_scalar everywhere)
    ior_scalar: float                 # one IOR for formats without an IOR texture
    specular_color: np.ndarray | None  # (H, W, 3) F0 tint in [0, 1] (None: white)
    transmittance: np.ndarray | None  # (H, W, 3) diffuse transmittance t, linear
    opacity: np.ndarray | None        # (H, W) coverage in [0, 1]
    texel_mm: float | None            # physical texel size (None: unknown)

    @property
    def shape(self) -> tuple[int, int]:
        return self.base_color.shape[0], self.base_color.shape[1]

    @property
    def size_mm(self) -> tuple[float, float] | None:
        """Physical (width, height) in mm of the maps, or ``None`` when the texel is unknown."""
        if not self.texel_mm:
            return None
        h, w = self.shape
        return w * self.texel_mm, h * self.texel_mm

    def alphas(self) -> tuple[np.ndarray, np.ndarray]:
        """GGX ``(alpha_t, alpha_b)`` ``(H, W)``: along the tangent and across it (Burley 2015,
        the mapping of :func:`dualscale.bsdf.ggx.ggx_alphas`, without its 1e-3 floor)."""
        a2 = self.roughness.astype(np.float64) ** 2
        if self.anisotropy is None:
            return a2, a2
        aspect = np.sqrt(1.0 - 0.9 * np.clip(self.anisotropy, 0.0, 1.0))
        return a2 / aspect, a2 * aspect


def exchange(maps: MaterialMaps, texel_mm: float | None = None, ior: float = DEFAULT_IOR) -> Exchange:
    """Convert :class:`~dualscale.bsdf.MaterialMaps` to :class:`Exchange` (exact: no information is
    dropped; the format functions below say what each format keeps).

    ``ior``: the model's constant IOR, used when there is no IOR map.  The tint is computed with
    :func:`dualscale.bsdf.terms.specular_tint`, the model's own definition (seed Sec. 5).
    """
    from dualscale.bsdf.terms import specular_tint

    validate_maps(maps)
    tint = None
    if maps.specular_tint is not None:
        tint = _np(specular_tint(maps.albedo, maps.specular_tint))
    eta = None if maps.ior is None else _np(ior_from_map(maps.ior))[..., 0]
    ior_scalar = float(np.median(eta)) if eta is not None else float(ior)
    tangent = None
    if maps.tangent is not None:
        tangent = np.remainder(_np(maps.tangent)[..., 0] * math.pi, math.pi).astype(np.float32)
    return Exchange(
        base_color=_np(maps.albedo), roughness=_np(maps.roughness)[..., 0],
        anisotropy=None if maps.anisotropy is None else _np(maps.anisotropy)[..., 0],
        tangent_angle=tangent, normal=_np(maps.normal), ior=eta, ior_scalar=ior_scalar,
        specular_color=tint, transmittance=_np(maps.transmittance),
        opacity=None if maps.opacity is None else _np(maps.opacity)[..., 0], texel_mm=texel_mm)


def f0_from_ior(eta: np.ndarray | float) -> np.ndarray | float:
    """Normal-incidence Fresnel reflectance of a dielectric, ``((eta - 1) / (eta + 1))^2``."""
    return ((np.asarray(eta) - 1.0) / (np.asarray(eta) + 1.0)) ** 2


# -- per-format re-parametrisations ---------------------------------------------------------------

def gltf_anisotropy(ex: Exchange) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``KHR_materials_anisotropy`` parameters ``(roughness, strength, direction)``.

    The extension stretches only along the tangent: ``alpha_b = r_g^2``,
    ``alpha_t = mix(r_g^2, 1, s^2)``.  We set ``r_g = sqrt(alpha_b)`` and
    ``s = sqrt((alpha_t - alpha_b) / (1 - alpha_b))``, which reproduces both of our alphas
    exactly (while ``alpha_t <= 1``; beyond, alpha_t is clamped to 1).  ``direction`` ``(H, W, 2)``
    is ``(cos phi, sin phi)`` in tangent space (+x right, +y up).  Isotropic maps return
    ``(roughness, None, None)``.
    """
    if ex.anisotropy is None or ex.tangent_angle is None:
        return ex.roughness, None, None
    at, ab = ex.alphas()
    at = np.minimum(at, 1.0)
    ab = np.minimum(ab, at)
    strength = np.sqrt(np.clip((at - ab) / np.maximum(1.0 - ab, 1e-9), 0.0, 1.0))
    phi = ex.tangent_angle.astype(np.float64)
    direction = np.stack([np.cos(phi), np.sin(phi)], -1)
    return np.sqrt(ab).astype(np.float32), strength.astype(np.float32), direction.astype(np.float32)


def standard_surface_anisotropy(ex: Exchange) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Autodesk Standard Surface ``(specular_roughness, specular_anisotropy, specular_rotation)``.

    Standard Surface (v1.0.1, as MaterialX implements it) uses ``aspect = sqrt(1 - a_s)``,
    ``alpha_x = r^2 / aspect``, ``alpha_y = r^2 aspect``: Burley's with ``a_s = 0.9 a``, so the
    roughness is ours and the anisotropy is scaled -- exact.  ``specular_rotation`` follows the
    specification's parameter table (v1.0.1, Specular): 0..1 turns the anisotropy 0..180 deg
    about the normal from the surface tangent (texture +u), counter-clockwise, so it is
    ``phi / pi``.  MaterialX 1.39.5's own graph instead turns ``360 * rotation`` degrees through
    ``rotate3d``, clockwise in its GLSL/OSL (MaterialX issue #2083); the MaterialX writer therefore
    leaves ``specular_rotation`` at 0 and connects the rotated ``tangent`` instead (:mod:`.mtlx`).
    """
    if ex.anisotropy is None or ex.tangent_angle is None:
        return ex.roughness, None, None
    rotation = (ex.tangent_angle.astype(np.float64) / math.pi).astype(np.float32)
    return ex.roughness, (0.9 * np.clip(ex.anisotropy, 0.0, 1.0)).astype(np.float32), rotation


def openpbr_anisotropy(ex: Exchange) -> tuple[np.ndarray, np.ndarray | None]:
    """OpenPBR Surface (v1.1) ``(specular_roughness, specular_roughness_anisotropy)``.

    OpenPBR maps ``(r, a_o)`` to ``alpha_t = min(1, r^2 sqrt(2 / (1 + (1 - a_o)^2)))`` and
    ``alpha_b = (1 - a_o) alpha_t``.  We solve for ``a_o = 1 - alpha_b / alpha_t`` and
    ``r = sqrt(alpha_t / sqrt(2 / (1 + (1 - a_o)^2)))``: exact while ``alpha_t <= 1``.  The
    direction is the tangent rotated by ``phi`` (:attr:`Exchange.tangent_angle`).
    """
    if ex.anisotropy is None:
        return ex.roughness, None
    at, ab = ex.alphas()
    at = np.minimum(at, 1.0)
    a_o = 1.0 - np.minimum(ab, at) / np.maximum(at, 1e-12)
    r = np.sqrt(at / np.sqrt(2.0 / (1.0 + (1.0 - a_o) ** 2)))
    return r.astype(np.float32), a_o.astype(np.float32)


@dataclass
class Transmission:
    """A thin-walled transmission split: ``base_color`` for what is reflected diffusely,
    ``weight`` (H, W) the fraction of the diffuse lobe that transmits, ``color`` its tint."""

    base_color: np.ndarray
    weight: np.ndarray
    color: np.ndarray


def gltf_transmission(ex: Exchange) -> Transmission | None:
    """``KHR_materials_transmission`` on a thin-walled surface (no ``KHR_materials_volume``).

    glTF scatters ``(1 - T) base`` diffusely and transmits ``T base`` (tinted by the base colour,
    through a microfacet BTDF of the same roughness).  One colour cannot hold both our ``b`` and
    ``t``, so the reflection, what most views see, is kept exactly: ``base = b / (1 - T)``, with
    ``T = Y(t) / Y(b + t)`` (the transmitted luminance ``Y(base) T = Y(t)`` is then ours too),
    lowered where needed to ``1 - max(b)`` so that no channel of ``base`` clips (then less is
    transmitted).  Lost: the chromaticity of ``t`` (glTF transmits with the base colour) and its
    diffuse angular shape.  ``None`` when the sample does not transmit.
    """
    if ex.transmittance is None:
        return None
    b, t = ex.base_color.astype(np.float64), ex.transmittance.astype(np.float64)
    yt, ytot = t @ LUMINANCE, (b + t) @ LUMINANCE
    weight = np.where(ytot > 1e-6, yt / np.maximum(ytot, 1e-6), 0.0)
    weight = np.minimum(weight, np.clip(1.0 - b.max(-1), 0.0, 1.0))
    base = np.clip(b / np.maximum(1.0 - weight, 1e-6)[..., None], 0, 1)
    return Transmission(base.astype(np.float32), weight.astype(np.float32), base.astype(np.float32))


def thin_walled_translucency(ex: Exchange) -> Transmission | None:
    """Our diffuse transmittance as a thin-walled *subsurface* lobe: Standard Surface with
    ``thin_walled = 1`` (whose subsurface becomes a Lambertian ``translucent_bsdf``) and OpenPBR's
    thin-walled subsurface -- the same diffuse transmission as ours (seed Sec. 5, ``t / pi``).

    ``weight = S``, ``base_color = b / (1 - S)`` and ``color = t / S`` (``subsurface_color``): exact
    per channel whenever some ``S`` in ``[max(t), 1 - max(b)]`` exists (i.e. ``max b + max t <= 1``);
    we take ``S = Y(t) / Y(b + t)`` clamped to that interval.  Where it is empty (very bright
    samples) ``S = 1 - max(b)`` keeps the reflection exact and the transmission colour clips
    (less is transmitted), as in :func:`gltf_transmission`.  ``None`` when opaque.
    """
    if ex.transmittance is None:
        return None
    b, t = ex.base_color.astype(np.float64), ex.transmittance.astype(np.float64)
    yt, ytot = t @ LUMINANCE, (b + t) @ LUMINANCE
    w = np.where(ytot > 1e-6, yt / np.maximum(ytot, 1e-6), 0.0)
    lo, hi = t.max(-1), 1.0 - b.max(-1)
    w = np.where(lo <= hi, np.clip(w, lo, hi), hi)
    w = np.clip(w, 0.0, 1.0)
    base = b / np.maximum(1.0 - w, 1e-6)[..., None]
    col = np.where(w[..., None] > 1e-6, t / np.maximum(w, 1e-6)[..., None], 1.0)
    return Transmission(np.clip(base, 0, 1).astype(np.float32), w.astype(np.float32),
                        np.clip(col, 0, 1).astype(np.float32))


def specular_f0_color(ex: Exchange) -> tuple[np.ndarray, float]:
    """For formats with one IOR and a specular-colour texture (glTF ``KHR_materials_specular``):
    ``(color, factor)`` with ``color * factor = tint * F0(eta_px) / F0(ior_scalar)`` per pixel,
    ``color`` in [0, 1] and ``factor >= 1`` only when the per-pixel IOR needs it.  The spatial
    IOR variation is thus kept at normal incidence (glTF's Schlick F0); its angular shape is not.
    """
    h, w = ex.shape
    tint = ex.specular_color if ex.specular_color is not None else np.ones((h, w, 3), np.float32)
    ratio = np.ones((h, w)) if ex.ior is None else f0_from_ior(ex.ior) / f0_from_ior(ex.ior_scalar)
    col = tint.astype(np.float64) * ratio[..., None]
    factor = float(max(1.0, col.max()))
    return (col / factor).astype(np.float32), factor


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec.709 relative luminance ``Y`` of linear RGB ``(..., 3)``."""
    return np.asarray(rgb, np.float64) @ LUMINANCE
