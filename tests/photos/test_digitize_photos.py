"""`dualscale digitize` on imported photographs: the stages that need our rig say why they are
skipped, and maps of photographs without a scale do not invent one."""

from __future__ import annotations

import json

import pytest

from dualscale.cli import main
from dualscale.formats.maps import load_maps


@pytest.mark.parametrize("texel", [None, "0.05"])
def test_digitize_imported_photos(sphere_set, tmp_path, texel):
    ds = tmp_path / "ds"
    extra = [] if texel is None else ["--texel-mm", texel]
    assert main(["import", str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(ds), "--transfer", "srgb",
                 "--no-progress", *extra]) == 0
    run = tmp_path / "run"
    assert main(["digitize", str(ds), "-o", str(run), "--quality", "draft", "--threads", "1", "--no-progress"]) == 0
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


def test_residual_leaves_out_pixels_that_were_not_fitted(sphere_set, tmp_path):
    """Outside the sample mask the residual map is NaN, so its statistics (the report's median)
    describe the sample, not the background."""
    import numpy as np

    from dualscale.formats.exr import read_exr
    from dualscale.formats.photo import read_mask

    ds = tmp_path / "ds"
    assert main(["import", str(sphere_set.folder), "--lights", str(sphere_set.lp), "-o", str(ds), "--transfer", "srgb",
                 "--no-progress"]) == 0
    run = tmp_path / "run"
    assert main(["digitize", str(ds), "-o", str(run), "--quality", "draft", "--until", "fit", "--threads", "1",
                 "--no-progress"]) == 0
    res = read_exr(run / "fit" / "residual.exr")[..., 0]
    mask = read_mask(ds / "mask.exr")
    assert np.isnan(res[~mask]).all() and np.isfinite(res[mask]).all()
