"""`dualscale digitize` on imported photographs: the stages that need our rig say why they are
skipped, and maps of photographs without a scale do not invent one."""

from __future__ import annotations

import json

import pytest

from dualscale.cli import main
from dualscale.formats.maps import load_maps
from photoset import lights_one_side, render_sphere


def _import_and_digitize(root, texel):
    """``(dataset, run folder)``: ``sphere_set``'s photographs imported (sRGB, ``--texel-mm
    texel`` unless None) and digitized at the draft quality, every stage."""
    s = render_sphere(root / "ball", lights_one_side())  # the conftest's sphere_set
    ds = root / "ds"
    extra = [] if texel is None else ["--texel-mm", texel]
    assert main(["import", str(s.folder), "--lights", str(s.lp), "-o", str(ds), "--transfer", "srgb",
                 "--no-progress", *extra]) == 0
    run = root / "run"
    assert main(["digitize", str(ds), "-o", str(run), "--quality", "draft", "--threads", "1", "--no-progress"]) == 0
    return ds, run


@pytest.fixture(scope="module")
def digitized(tmp_path_factory):
    """The run without a physical size, shared by the tests that only read it (one import and
    digitize instead of two)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)  # as the autouse one_thread fixture, which is function-scoped
    try:
        return _import_and_digitize(tmp_path_factory.mktemp("digitized"), None)
    finally:
        torch.set_num_threads(n)


@pytest.mark.parametrize("texel", [None, "0.05"])
def test_digitize_imported_photos(digitized, tmp_path, texel):
    ds, run = digitized if texel is None else _import_and_digitize(tmp_path, texel)
    stages = {s: json.loads((run / "stages" / f"{s}.json").read_text())["summary"]
              for s in ("flyouts", "propagate")}
    assert "polarised" in stages["flyouts"]["skipped"] and "guidance" in stages["propagate"]["skipped"]
    _, meta = load_maps(run / "export" / "micro" / "maps")
    exp = json.loads((run / "export" / "micro" / "export.json").read_text())
    warnings = json.loads((run / "stages" / "export.json").read_text())["warnings"]
    if texel is None:  # no physical size: every format but U3M, which needs one (a warning says so)
        assert meta["texel_mm"] is None and meta["field_mm"] is None
        assert "u3m" not in exp["formats"] and "u3m" in exp["skipped"] and any("U3M" in w for w in warnings)
        assert {"exr", "mtlx", "gltf", "glb"} <= set(exp["formats"])
    else:
        assert set(exp["formats"]) == {"maps", "exr", "mtlx", "gltf", "glb", "u3m"}
        assert meta["texel_mm"] == pytest.approx(0.05) and meta["field_mm"] == pytest.approx([2.0, 2.0])
    assert (run / "report" / "index.html").is_file()


def test_residual_leaves_out_pixels_that_were_not_fitted(digitized):
    """Outside the sample mask the residual map is NaN, so its statistics (the report's median)
    describe the sample, not the background.  (The fit stage of the shared full run: the same
    stage ``--until fit`` runs.)"""
    import numpy as np

    from dualscale.formats.exr import read_exr
    from dualscale.formats.photo import read_mask

    ds, run = digitized
    res = read_exr(run / "fit" / "residual.exr")[..., 0]
    mask = read_mask(ds / "mask.exr")
    assert np.isnan(res[~mask]).all() and np.isfinite(res[mask]).all()
