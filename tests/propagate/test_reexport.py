"""A model replaced by an older file (issue 24 §7): ``propagate run`` and the propagate stage decide
by content whether to re-export the ONNX beside a model file -- the SHA-256 of the model file
recorded in the export's metadata -- not by modification time, so a model copied in with
``cp -p`` (an older time than the exports) runs the new network, and an unchanged model is not
exported again."""

from __future__ import annotations

import os
import shutil

import numpy as np
import onnx
import pytest
import torch

from dualscale.cli import main
from dualscale.formats.exr import read_exr, write_exr
from dualscale.formats.model import read_model_file, write_model_file
from dualscale.propagate.export import (SOURCE_KEY, ensure_exported, exports_current, file_sha256, onnx_paths,
                                        recorded_source)

OLD = 946684800  # 2000-01-01: the time an archived model file keeps through cp -p


def _other_model(src, dst):
    """A second model of the same architecture with other weights (a retrained network)."""
    doc = read_model_file(src)
    gen = torch.Generator().manual_seed(7)
    sd = {k: (v + 0.5 * torch.randn(v.shape, generator=gen, dtype=v.dtype) if v.is_floating_point() else v)
          for k, v in doc["state_dict"].items()}
    write_model_file(dst, doc["config"], sd, doc["input_reference"], doc["train"])
    return dst


def _cp_p(src, dst):
    """``cp -p src dst`` with ``src`` carrying an old time: content replaced, time older than before."""
    shutil.copyfile(src, dst)
    os.utime(dst, (OLD, OLD))


@pytest.fixture
def models(tiny_model, tmp_path):
    a = tmp_path / "a.dsp"
    shutil.copy(tiny_model, a)
    b = _other_model(a, tmp_path / "b.dsp")
    return a, b


def _guidance(tmp_path):
    img = (0.2 + 0.3 * np.random.default_rng(3).random((48, 48, 3))).astype(np.float32)
    write_exr(tmp_path / "g.exr", img)
    return tmp_path / "g.exr"


def _run(model, guidance, out):
    assert main(["propagate", "run", str(model), str(guidance), "-o", str(out), "--exposure", "1", "--tile", "48",
                 "--overlap", "0", "--precision", "fp32", "--no-progress", "--threads", "1"]) == 0
    return read_exr(out / "albedo.exr")


def test_propagate_run_reexports_a_model_replaced_by_an_older_file(models, tmp_path):
    a, b = models
    g = _guidance(tmp_path)
    ref_b = _run(b, g, tmp_path / "ref_b")  # what network b gives (exported beside b.dsp)
    work = tmp_path / "work"
    work.mkdir()
    model = work / "m.dsp"
    shutil.copy(a, model)
    out_a = _run(model, g, tmp_path / "out_a")
    assert not np.allclose(out_a, ref_b, atol=1e-3)  # the two networks differ visibly
    p32, p16 = onnx_paths(model)
    assert model.stat().st_mtime < p32.stat().st_mtime  # the exports are newer than the model
    _cp_p(b, model)
    assert model.stat().st_mtime < p32.stat().st_mtime  # ... and still newer after the copy
    out_b = _run(model, g, tmp_path / "out_b")
    assert np.array_equal(out_b, ref_b), "propagate run used the old network's ONNX"
    assert recorded_source(p32) == recorded_source(p16) == file_sha256(b)


def test_an_unchanged_model_is_not_exported_again(models):
    a, _ = models
    assert ensure_exported(a, check=False) is not None  # none yet: exported
    p32, p16 = onnx_paths(a)
    stamps = [p.stat().st_mtime_ns for p in (p32, p16)]
    os.utime(a, None)  # a newer time, same content (touch, a checkout): no re-export
    assert ensure_exported(a, check=False) is None
    assert [p.stat().st_mtime_ns for p in (p32, p16)] == stamps


def test_the_stage_decision_follows_content_not_time(models):
    """``ensure_exported`` is the propagate stage's decision too: a replaced model (older time)
    is exported again, with parity; an export that records no hash (made by an earlier version)
    or another model's hash is stale; a damaged export is stale."""
    a, b = models
    ex = ensure_exported(a, check=True)
    assert ex is not None and max(ex["parity_fp32"].values()) < 1e-4
    assert exports_current(a)
    p32, p16 = onnx_paths(a)
    _cp_p(b, a)
    assert not exports_current(a)
    assert ensure_exported(a, check=True) is not None
    assert exports_current(a) and recorded_source(p32) == file_sha256(b)
    # an export without the hash (an earlier dualscale) is stale
    proto = onnx.load(str(p16))
    keep = [(e.key, e.value) for e in proto.metadata_props if e.key != SOURCE_KEY]
    del proto.metadata_props[:]
    for k, v in keep:
        e = proto.metadata_props.add()
        e.key, e.value = k, v
    onnx.save(proto, str(p16))
    assert recorded_source(p16) is None and not exports_current(a)
    assert ensure_exported(a, check=False) is not None and exports_current(a)
    p32.write_bytes(p32.read_bytes()[:100])  # a damaged export
    assert recorded_source(p32) is None and not exports_current(a)
