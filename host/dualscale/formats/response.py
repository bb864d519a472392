"""Camera responses: how a photograph's normalised code values map to linear radiance.

A response is a monotone curve pair on ``[0, 1]``: the *inverse response* ``g`` (code value ->
linear, what decoding applies) and the *response* ``f = g^-1`` (linear -> code value), with
``g(0) = 0`` and ``g(1) = 1`` (the top code is the linear value 1; the linear scale of an image
is the light scale's business, :mod:`dualscale.calib.photo_import`).  The families, in the
``method=`` registry style of colour-science (:data:`FAMILIES`):

* ``linear`` -- ``g(c) = c`` (raw-developed linear TIFFs), no parameter;
* ``srgb`` -- IEC 61966-2-1 through colour-science (``colour.cctf_decoding(c, "sRGB")``), no
  parameter;
* ``gamma`` -- a pure power law ``g(c) = c ** G``, one parameter ``G`` (``V = L ** (1/G)``);
* ``curve`` -- a monotone curve containing the power laws: ``g(c) = G(c) / G(1)`` with
  ``G(c) = int_0^c t^(G - 1) exp(sum_j a_j P_j(2 t - 1)) dt`` (``P_j`` Legendre polynomials,
  ``j = 1..D``); parameters ``(G, a_1, ..., a_D)``.  Monotone by construction, and a gamma for
  ``a = 0``: the low-dimensional monotone model of the response-calibration literature
  (Mitsunaga & Nayar, CVPR 1999 fit a polynomial; Grossberg & Nayar's EMoR, TPAMI 2004, a PCA
  basis of measured curves, is not shipped: its database is not on the package registries).

A :class:`Response` also records where it came from (``source``: ``"stated"``, ``"auto"`` --
estimated from the photographs, :mod:`dualscale.calib.response` -- or ``"target"``, from a
matte reference sphere), its uncertainty and the evidence for it; :meth:`Response.to_json` /
:func:`response_from_json` are its one writer and reader (datasets' ``extra.import.response``,
light files' ``source.response``).

``transfer`` strings (``--transfer``, a dataset's ``transfer`` field): ``linear``, ``srgb``,
``gamma:G``, and ``curve`` (the curve itself is in the record's ``response`` block).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dualscale.errors import FormatError, UnitsError

FAMILIES = ("linear", "srgb", "gamma", "curve")
#: Legendre terms of the ``curve`` family
CURVE_DEGREE = 6
#: grid of the curve family's numerical integral (cells on [0, 1])
_GRID = 2048
GAMMA_RANGE = (0.2, 5.0)
#: the transfers a user can state (``--transfer``)
TRANSFERS = ("srgb", "linear", "gamma:G")


def _srgb_inverse(c: np.ndarray) -> np.ndarray:
    import colour

    return np.asarray(colour.cctf_decoding(np.clip(c, 0.0, 1.0), function="sRGB"), np.float64)


def curve_table(params: np.ndarray | list[float], n: int = _GRID) -> tuple[np.ndarray, np.ndarray]:
    """``(t, g)``: the ``curve`` family's inverse response on ``n + 1`` codes ``t = 0 .. 1``
    (module doc).  Integrated cell by cell: the power part exactly, the exponential's
    polynomial at the cell's midpoint.  ``g`` is strictly increasing, ``g[0] = 0``, ``g[-1] = 1``."""
    p = np.asarray(params, np.float64)
    gam, a = float(p[0]), p[1:]
    t = np.linspace(0.0, 1.0, n + 1)
    mid = 0.5 * (t[1:] + t[:-1])
    poly = np.polynomial.legendre.legval(2.0 * mid - 1.0, np.concatenate([[0.0], a])) if a.size else 0.0 * mid
    poly = poly - poly.max()  # the scale cancels in G(c) / G(1); this keeps exp() finite
    cell = np.exp(poly) * (t[1:] ** gam - t[:-1] ** gam) / gam
    g = np.concatenate([[0.0], np.cumsum(cell)])
    return t, g / g[-1]


@dataclass
class Response:
    """A camera response (module doc).  ``family`` one of :data:`FAMILIES`; ``params`` its
    parameters (``()``, ``(G,)``, or ``(G, a_1..a_D)``); ``source`` ``"stated" | "auto" |
    "target"``; ``uncertainty`` and ``evidence`` free-form JSON (what the estimator measured)."""

    family: str
    params: tuple[float, ...] = ()
    source: str = "stated"
    uncertainty: dict[str, Any] = field(default_factory=dict)
    evidence: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise UnitsError(f"unknown response family {self.family!r}; one of {', '.join(FAMILIES)}")
        self.params = tuple(float(x) for x in self.params)
        need = {"linear": 0, "srgb": 0, "gamma": 1}.get(self.family)
        if need is not None and len(self.params) != need:
            raise UnitsError(f"response {self.family}: {need} parameter(s), got {len(self.params)}")
        if self.family == "curve" and len(self.params) < 1:
            raise UnitsError("response curve: needs at least the power G")
        if self.family in ("gamma", "curve"):
            g = self.params[0]
            if not (math.isfinite(g) and GAMMA_RANGE[0] <= g <= GAMMA_RANGE[1]):
                raise UnitsError(f"response {self.family}: the power must be in {GAMMA_RANGE}, got {g}")
        if not all(math.isfinite(x) for x in self.params):
            raise UnitsError(f"response {self.family}: parameters {self.params} are not finite")
        self._table: tuple[np.ndarray, np.ndarray] | None = None

    # -- the curves ------------------------------------------------------------------------
    def table(self, n: int = _GRID) -> tuple[np.ndarray, np.ndarray]:
        """``(code, linear)`` on ``n + 1`` codes over [0, 1] (cached for the default ``n``)."""
        if n == _GRID and self._table is not None:
            return self._table
        t = np.linspace(0.0, 1.0, n + 1)
        if self.family == "curve":
            out = curve_table(self.params, n)
        else:
            out = (t, self.inverse(t))
        if n == _GRID:
            self._table = out
        return out

    def inverse(self, code: np.ndarray | float) -> np.ndarray:
        """``g``: normalised code values (clipped to [0, 1]) -> linear values in [0, 1], float64."""
        c = np.clip(np.asarray(code, np.float64), 0.0, 1.0)
        if self.family == "linear":
            return c
        if self.family == "gamma":
            return c ** self.params[0]
        if self.family == "srgb":
            return _srgb_inverse(c)
        t, g = self.table()
        return np.interp(c, t, g)

    def forward(self, linear: np.ndarray | float) -> np.ndarray:
        """``f = g^-1``: linear values (clipped to [0, 1]) -> normalised code values, float64."""
        x = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
        if self.family == "linear":
            return x
        if self.family == "gamma":
            return x ** (1.0 / self.params[0])
        t, g = self.table() if self.family == "curve" else self.table(4096)
        return np.interp(x, g, t)

    def slope(self, code: np.ndarray) -> np.ndarray:
        """``g'(c)`` (linear per unit code), by central differences on the table; > 0."""
        t, g = self.table() if self.family == "curve" else self.table(4096)
        d = np.gradient(g, t)
        return np.maximum(np.interp(np.clip(code, 0.0, 1.0), t, d), 1e-9)

    # -- names and records -------------------------------------------------------------------
    @property
    def transfer(self) -> str:
        """The ``--transfer`` / dataset string: ``linear``, ``srgb``, ``gamma:G`` or ``curve``."""
        if self.family == "gamma":
            return f"gamma:{self.params[0]:.4g}"
        return self.family

    def describe(self) -> str:
        """One line for people: the family, its power and where it came from."""
        u = self.uncertainty.get("gamma_std")
        if self.family == "gamma":
            s = f"gamma {self.params[0]:.3f}" + (f" ± {u:.3f}" if u is not None else "")
        elif self.family == "curve":
            s = f"monotone curve (power {self.params[0]:.3f}, {len(self.params) - 1} Legendre terms)"
            m = self.uncertainty.get("curve_std_max")
            if m is not None:
                s += f", ±{100 * m:.2f} % of full scale"
        else:
            s = self.family
        return s + {"stated": " (stated)", "auto": " (estimated from the photographs)",
                    "target": " (from the matte reference sphere)"}.get(self.source, f" ({self.source})")

    def to_json(self) -> dict[str, Any]:
        """The record (the one writer): family, params, transfer, source, a 33-code table of
        ``g`` (for tools that do not evaluate the family), uncertainty and evidence."""
        c = np.linspace(0.0, 1.0, 33)
        return {"family": self.family, "params": list(self.params), "transfer": self.transfer,
                "source": self.source, "table": {"code": c.round(6).tolist(),
                                                 "linear": self.inverse(c).round(7).tolist()},
                "uncertainty": self.uncertainty, "evidence": self.evidence}


def response_from_json(doc: Any, where: str) -> Response:
    """Read a :meth:`Response.to_json` record; :class:`FormatError` naming ``where``."""
    if not isinstance(doc, dict) or "family" not in doc:
        raise FormatError(f"{where}: a response record needs 'family' and 'params'")
    try:
        return Response(str(doc["family"]), tuple(doc.get("params") or ()), str(doc.get("source", "stated")),
                        dict(doc.get("uncertainty") or {}), dict(doc.get("evidence") or {}))
    except (TypeError, ValueError) as e:
        raise FormatError(f"{where}: response: {e}") from e


def stated_response(transfer: str) -> Response:
    """The :class:`Response` a stated ``--transfer`` names (``linear``, ``srgb``, ``gamma:G``);
    :class:`UnitsError` otherwise (``auto`` and ``curve`` are not decodings one can state)."""
    kind, g = parse_transfer(transfer)
    return Response(kind, () if g is None else (g,), "stated")


def parse_transfer(transfer: str | None) -> tuple[str, float | None]:
    """``("srgb" | "linear" | "gamma", G or None)``; :class:`~dualscale.errors.UnitsError`
    for anything else."""
    if transfer is None:
        raise UnitsError("the transfer function of display-encoded images must be stated: "
                         "--transfer srgb|linear|gamma:G (dualscale never guesses it)")
    t = transfer.strip().lower()
    if t in ("auto", "lights"):
        raise UnitsError(f"--transfer {t}: the response is estimated from a set of photographs under several lights "
                         "(dualscale import, dualscale lights sphere --matte); here it must be stated: "
                         "srgb|linear|gamma:G (the import's estimate is in the dataset's "
                         "extra.import.radiometry)")
    if t in ("srgb", "linear"):
        return t, None
    if t.startswith("gamma:"):
        try:
            g = float(t[6:])
        except ValueError:
            g = float("nan")
        if not (np.isfinite(g) and 0.2 <= g <= 5.0):
            raise UnitsError(f"transfer {transfer!r}: the gamma must be a number between 0.2 and 5")
        return "gamma", g
    raise UnitsError(f"unknown transfer function {transfer!r}; use one of {', '.join(TRANSFERS)}")


def radiometry_summary(manifest: dict[str, Any]) -> dict[str, Any] | None:
    """What a dataset's ``manifest.json`` says of its photographs' radiometry, for the fit's
    records, the report and the exports: ``{"transfer", "response", "source", "family",
    "params", "intensities"}`` (``response`` a line for people, ``intensities`` where the lights'
    relative intensities came from), or None for a dataset that was not imported from
    photographs (the rig's calibrated captures)."""
    imp = ((manifest or {}).get("extra") or {}).get("import")
    if not isinstance(imp, dict):
        return None
    rad = imp.get("radiometry") or {}
    resp = rad.get("response")
    out: dict[str, Any] = {"transfer": manifest.get("transfer"),
                           "intensities": rad.get("intensities_source") or "file"}
    if isinstance(resp, dict):
        try:
            r = response_from_json(resp, "manifest.json")
        except FormatError:
            r = None
        if r is not None:
            out.update({"response": r.describe(), "source": r.source, "family": r.family,
                        "params": list(r.params)})
    else:
        out.update({"response": str(manifest.get("transfer") or "linear (EXR)"), "source": "stated"})
    if rad.get("warnings"):
        out["warnings"] = list(rad["warnings"])
    return out
