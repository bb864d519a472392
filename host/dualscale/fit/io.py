"""Fitted maps on disk: the maps through :func:`dualscale.formats.maps.save_maps` (so every
tool reads them), each EXR carrying the fit's metadata, plus ``fit.json`` (the full report).

EXR header attributes (strings): ``dualscale:preset``, ``dualscale:components`` (JSON),
``dualscale:iterations``, ``dualscale:final_losses`` (JSON), ``dualscale:selection`` (JSON:
the component decision and its evidence), ``dualscale:map``.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from dualscale.formats.atomic import remove_file, write_json
from dualscale.formats.exr import read_exr_attributes
from dualscale.formats.maps import save_maps

from .core import FitResult

def fit_attributes(res: FitResult, selection: dict | None) -> dict[str, str]:
    return {"dualscale:preset": res.preset.name,
            "dualscale:components": json.dumps(asdict(res.comps)),
            "dualscale:iterations": str(res.iterations),
            "dualscale:final_losses": json.dumps(res.losses),
            "dualscale:selection": json.dumps(selection or {})}


def save_fit(root: str | Path, res: FitResult, selection: dict | None = None, extra: dict | None = None,
             previews: bool = True, texel_mm: float | None = None) -> Path:
    """Write the maps of ``res`` under ``root`` (``texel_mm``: the dataset's pixel pitch);
    returns the path of ``fit.json``.

    ``fit.json`` is the fit's completion record: an earlier one is removed first and the new one
    is written last, after every map and ``material.json``, each atomically; a write that fails
    (a full disk) leaves no ``fit.json``, and no map file is ever short or empty."""
    root = Path(root)
    report, meta = _report(res, selection, extra)
    remove_file(root / "fit.json")
    save_maps(root, res.maps, meta, previews, texel_mm=texel_mm, attributes=fit_attributes(res, selection))
    _save_uncertainty(root, res, report)
    return write_json(root / "fit.json", report)


def _save_uncertainty(root: Path, res: FitResult, report: dict[str, Any]) -> None:
    """The uncertainty of ``res`` into ``root/uncertainty/`` and its summary into ``report``
    (``fit.json``'s ``"uncertainty"``, :func:`.uncertainty.summary`); a fit without one
    removes an earlier fit's record, so no stale uncertainty sits beside new maps.  Its record's
    ``meta.maps_sha256`` (:func:`~dualscale.formats.maps.maps_sha256`) names the maps it belongs
    to: ``dualscale export`` refuses an uncertainty copied in from another fit."""
    from dualscale.formats.maps import maps_sha256, save_uncertainty

    from .uncertainty import summary

    u = res.uncertainty
    if u is None:
        _drop_uncertainty(root)
        return
    sigma, und = u.arrays()
    save_uncertainty(root, sigma, und, {"noise": u.noise, "preset": res.preset.name, "maps_sha256": maps_sha256(root)})
    report["uncertainty"] = summary(sigma, und, u.noise, u.seconds)


def _drop_uncertainty(root: Path) -> None:
    """Remove an earlier fit's ``root/uncertainty/``: its record first (so no reader sees a
    partial set), then its maps and the folder."""
    from dualscale.formats.maps import UNCERTAINTY_DIR

    folder = root / UNCERTAINTY_DIR
    remove_file(folder / "uncertainty.json")
    if folder.is_dir():
        for p in folder.glob("*.exr"):
            remove_file(p)
        try:
            folder.rmdir()
        except OSError:  # something else is in there: left alone
            pass


def save_fit_rows(root: str | Path, res: FitResult, shape: tuple[int, int], names: list[str], rows: Iterable,
                  selection: dict | None = None, extra: dict | None = None, previews: bool = True,
                  texel_mm: float | None = None, uncertainty=None) -> Path:
    """:func:`save_fit` of a fit out of core (``res.maps`` is ``None``): the maps ``names`` of a
    ``(H, W)`` map come as ``rows``, ``(y0, {name: (n, W, C) float32})`` strips in order
    (:func:`.stream.write_rows`), and go through :class:`~dualscale.formats.maps.MapsWriter`;
    the same files, headers and ``fit.json``, written in the same order.  ``uncertainty``: the
    fit's :class:`.stream.UncertaintyRows`, written by rows through
    :class:`~dualscale.formats.maps.UncertaintyWriter` with its summary in ``fit.json``
    (:class:`_Spill`); ``None`` removes an earlier fit's, as :func:`save_fit` does."""
    from dualscale.formats.maps import MapsWriter, UncertaintyWriter, maps_sha256

    root = Path(root)
    report, meta = _report(res, selection, extra)
    remove_file(root / "fit.json")
    with MapsWriter(root, names, shape[0], shape[1], meta, previews, texel_mm=texel_mm,
                    attributes=fit_attributes(res, selection)) as out:
        for y0, strip in rows:
            out.write(y0, strip)
    if uncertainty is None:
        _drop_uncertainty(root)
    else:
        with tempfile.TemporaryDirectory(dir=root, prefix=".tmp-sigma-") as tmp, \
                UncertaintyWriter(root, uncertainty.names, shape[0], shape[1],
                                  {"noise": uncertainty.noise, "preset": res.preset.name,
                                   "maps_sha256": maps_sha256(root)}) as uw:
            spill = _Spill(Path(tmp), uncertainty.names, shape)
            for y0, sigma, und in uncertainty.strips:
                uw.write(y0, sigma, und)
                spill.put(y0, sigma, und)
            report["uncertainty"] = spill.summary(uncertainty.noise, uncertainty.seconds)
    return write_json(root / "fit.json", report)


class _Spill:
    """The float32 sigma and the mask of a fit out of core's uncertainty, spilled by rows to one
    memory-mapped file per map under ``folder`` (removed by the caller), so that fit.json's
    summary (:func:`.uncertainty.summary`: medians, p90 over the whole map) is that of the
    in-memory fit, the same float32 values, with one map in memory at a time: its ``(H, W, C)``
    float32 sigma, the float64 copy ``summary`` takes and the mask (C <= 3: <= 39 bytes a pixel,
    650 MiB at 4096^2).  Disk: 4 bytes a value and 1 a mask entry, beside the maps."""

    def __init__(self, folder: Path, names: list[str], shape: tuple[int, int]) -> None:
        from dualscale.formats.maps import SIGMA_CHANNELS

        self.files = {n: (folder / f"{n}.f32", folder / f"{n}.u8", (*shape, SIGMA_CHANNELS[n])) for n in names}
        for f32, u8, full in self.files.values():
            np.lib.format.open_memmap(f32, "w+", np.float32, full).flush()
            np.lib.format.open_memmap(u8, "w+", np.uint8, full).flush()

    def put(self, y0: int, sigma: dict[str, Any], und: dict[str, Any]) -> None:
        for n, (f32, u8, full) in self.files.items():
            s, u = np.asarray(sigma[n], np.float32), np.asarray(und[n], np.uint8)
            s, u = s.reshape(s.shape[0], *full[1:]), u.reshape(u.shape[0], *full[1:])
            for path, a in ((f32, s), (u8, u)):
                m = np.load(path, mmap_mode="r+")
                m[y0:y0 + a.shape[0]] = a
                m.flush()
                del m

    def summary(self, noise: str, seconds: float) -> dict[str, Any]:
        from .uncertainty import summary

        rec: dict[str, Any] | None = None
        for n, (f32, u8, _) in self.files.items():
            part = summary({n: np.load(f32)}, {n: np.load(u8).astype(bool)}, noise, seconds)
            rec = part if rec is None else {**rec, "maps": {**rec["maps"], **part["maps"]}}
        assert rec is not None
        return rec


def _report(res: FitResult, selection: dict | None, extra: dict | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """``fit.json``'s record and ``material.json``'s ``meta`` of a fit."""
    report: dict[str, Any] = {
        "preset": asdict(res.preset), "components": asdict(res.comps), "iterations": res.iterations,
        "seconds": res.seconds, "final_losses": res.losses, "selection": selection or {},
        "resumed_from_iteration": res.resumed_from, "loss_history": res.history[-200:], **(extra or {})}
    meta = {"fit": {k: report[k] for k in ("preset", "components", "iterations", "final_losses")},
            "ior": res.comps.ior}
    if report.get("radiometry"):  # photographs: the camera response the maps were fitted under
        meta["radiometry"] = report["radiometry"]
    return report, meta


def read_fit_attributes(path: str | Path) -> dict[str, Any]:
    """The ``dualscale:*`` attributes of a fitted EXR, JSON values decoded."""
    out: dict[str, Any] = {}
    for key, val in read_exr_attributes(path).items():
        try:
            out[key] = json.loads(val) if key in ("components", "final_losses", "selection") else val
        except (TypeError, json.JSONDecodeError):
            out[key] = val
    return out
