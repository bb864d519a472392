"""Camera models of the rig: pixel -> sample-plane point and view direction, analyser axis.

Sample plane ``z = 0`` in the macro frame of :mod:`.geometry`, positions in mm, origin at the
dome centre.  Image convention (also the map convention): row 0 is the top (``+y``), column 0
is the left (``-x``); image ``+x`` is world ``+x`` for the micro and mid cameras.  The analyser
angle is measured counter-clockwise from the camera's image ``+x`` axis, in degrees.
"""

from __future__ import annotations

from typing import Any

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dualscale.protocol import regmap

D64 = torch.float64


def _unit(x: Tensor) -> Tensor:
    return x / x.norm(dim=-1, keepdim=True)


@dataclass(frozen=True)
class Camera:
    """A camera imaging the sample plane.

    ``kind='orthographic'``: looks straight down, ``field_mm`` is the imaged area.
    ``kind='perspective'``: pinhole at ``position_mm`` looking at the origin; ``field_mm`` is the
    width/height of the field at the origin measured perpendicular to the optical axis.
    """

    name: str
    kind: str
    width: int
    height: int
    field_mm: tuple[float, float]
    position_mm: tuple[float, float, float] = (0.0, 0.0, 400.0)
    has_analyzer: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("orthographic", "perspective"):
            raise ValueError(f"camera kind must be 'orthographic' or 'perspective', got {self.kind!r}")
        for what, v in (("width", self.width), ("height", self.height), ("field_mm[0]", self.field_mm[0]),
                        ("field_mm[1]", self.field_mm[1])):
            if not (v > 0 and v < float("inf")):
                raise ValueError(f"{what} must be a positive finite number, got {v}")
        if self.kind == "perspective" and self.position_mm[2] <= 0:
            raise ValueError("a perspective camera must sit above the sample (z > 0)")

    @classmethod
    def from_json(cls, name: str, d: Any, where: str = "camera") -> "Camera":
        """The one reader of a camera record ``{kind, width, height, field_mm, position_mm,
        has_analyzer}`` (datasets, captures, calibrations).  ``ValueError`` naming ``where`` and
        the field for a missing or malformed value (e.g. ``field_mm: null``)."""
        try:
            if not isinstance(d, dict):
                raise TypeError("not an object")
            field = tuple(float(v) for v in d["field_mm"])
            pos = tuple(float(v) for v in d.get("position_mm", (0.0, 0.0, 400.0)))
            if len(field) != 2 or len(pos) != 3:
                raise ValueError("field_mm needs 2 lengths and position_mm 3")
            return cls(name=name, kind=str(d["kind"]), width=int(d["width"]), height=int(d["height"]),
                       field_mm=field, position_mm=pos,  # type: ignore[arg-type]
                       has_analyzer=bool(d.get("has_analyzer", False)))
        except KeyError as e:
            raise ValueError(f"{where}: camera {name!r} has no {e.args[0]!r}") from e
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: camera {name!r} is malformed ({e}); it needs kind, width, height, "
                             "field_mm [w, h] in mm and position_mm [x, y, z] in mm") from e

    @property
    def pixel_mm(self) -> tuple[float, float]:
        return self.field_mm[0] / self.width, self.field_mm[1] / self.height

    def basis(self) -> tuple[Tensor, Tensor, Tensor]:
        """World-space ``(right, up, forward)`` unit vectors of the image plane / optical axis."""
        if self.kind == "orthographic":
            return (torch.tensor([1.0, 0, 0], dtype=D64), torch.tensor([0, 1.0, 0], dtype=D64),
                    torch.tensor([0, 0, -1.0], dtype=D64))
        c = torch.tensor(self.position_mm, dtype=D64)
        fwd = _unit(-c)
        # image +x follows world +x (projected) unless the camera looks along x; then use +y
        ref = torch.tensor([0, 1.0, 0], dtype=D64) if abs(float(fwd[1])) < 0.999 else torch.tensor([0, 0, 1.0], dtype=D64)
        right = _unit(torch.linalg.cross(fwd, ref, dim=-1))
        up = torch.linalg.cross(right, fwd, dim=-1)
        return right, up, fwd

    def _ndc(self) -> tuple[Tensor, Tensor]:
        xs = ((torch.arange(self.width, dtype=D64) + 0.5) / self.width - 0.5)
        ys = (0.5 - (torch.arange(self.height, dtype=D64) + 0.5) / self.height)
        y, x = torch.meshgrid(ys, xs, indexing="ij")
        return x, y

    def pixel_geometry(self) -> tuple[Tensor, Tensor]:
        """``(points (H, W, 2) [mm], view (3,) or (H, W, 3))`` for every pixel centre (float64).

        ``view`` points from the sample point towards the camera.
        """
        x, y = self._ndc()
        if self.kind == "orthographic":
            pts = torch.stack([x * self.field_mm[0], y * self.field_mm[1]], -1)
            return pts, torch.tensor([0.0, 0.0, 1.0], dtype=D64)
        c = torch.tensor(self.position_mm, dtype=D64)
        right, up, fwd = self.basis()
        dist = float(c.norm())
        d = fwd * dist + right * (x[..., None] * self.field_mm[0]) + up * (y[..., None] * self.field_mm[1])
        if bool((d[..., 2] >= 0).any()):
            raise ValueError(f"camera {self.name!r}: some pixels do not see the sample plane")
        t = -c[2] / d[..., 2]
        p = c + t[..., None] * d
        return p[..., :2], _unit(c - p)

    def analyzer_axis(self, angle_deg: float) -> Tensor:
        """World-space unit transmission axis of an analyser at ``angle_deg`` on the image plane."""
        right, up, _ = self.basis()
        a = math.radians(angle_deg)
        return math.cos(a) * right + math.sin(a) * up


def micro_camera(size: int = 512, pixel_um: float = 1.8, height: int | None = None) -> Camera:
    """Orthographic micro camera with a rotatable analyser; one pixel per map texel."""
    h = size if height is None else height
    return Camera(regmap.CAMERA_NAMES[0], "orthographic", size, h, (size * pixel_um / 1000, h * pixel_um / 1000),
                  has_analyzer=True)


def mid_camera(size: int = 512, field_mm: float = 100.0, distance_mm: float = 400.0) -> Camera:
    """Perspective mid-range camera above the sample with a 10 x 10 cm field."""
    return Camera(regmap.CAMERA_NAMES[1], "perspective", size, size, (field_mm, field_mm), (0.0, 0.0, distance_mm))


def polar_camera(index: int, size: int = 512, theta_deg: float = 45.0, phi_deg: float | None = None,
                 distance_mm: float = 400.0, field_mm: float = 100.0) -> Camera:
    """Oblique perspective camera ``polar<index>`` at polar angle ``theta_deg`` (analyser fitted)."""
    phi = 90.0 * index if phi_deg is None else phi_deg
    t, p = math.radians(theta_deg), math.radians(phi)
    pos = (distance_mm * math.sin(t) * math.cos(p), distance_mm * math.sin(t) * math.sin(p), distance_mm * math.cos(t))
    return Camera(regmap.CAMERA_NAMES[2 + index], "perspective", size, size, (field_mm, field_mm), pos,
                  has_analyzer=True)


def rig_cameras(micro_size: int = 512, other_size: int = 512) -> dict[str, Camera]:
    """All cameras of the rig, keyed by ``regmap.CAMERA_NAMES``."""
    cams = [micro_camera(micro_size), mid_camera(other_size), polar_camera(0, other_size), polar_camera(1, other_size)]
    return {c.name: c for c in cams}
