"""ONNX export (fp32, fp16 and, on request, int8) and the parity check against PyTorch.

The graph takes ``image`` ``(N, 3, H, W)`` linear RGB (``H``, ``W`` multiples of 16, dynamic)
and returns ``maps`` ``(N, C, H, W)``, the maps concatenated in the order stored in the ONNX
metadata (``dualscale:maps``, JSON).  The fp16 graph has float16 input and output.  The int8
graph (:func:`quantize_int8`) is onnxruntime's dynamic quantisation of the fp32 graph
(``onnxruntime.quantization.quantize_dynamic``: uint8 weights, activations quantised per run,
``ConvInteger``); float32 input and output.  Its accuracy loss per map is measured in
docs/PROPAGATION.md; it is never chosen by default.

Every export records the SHA-256 of the model file it was made from (``dualscale:source_sha256``),
and :func:`ensure_exported` -- what ``dualscale propagate run`` and the propagate stage call --
re-exports when that differs from the model file's content or is absent.  The decision is by
content, not modification time: a model file replaced by another one with an older time
(``cp -p``, ``rsync -t``, an archive) is re-exported, and an unchanged one is not.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import warnings
from pathlib import Path

import numpy as np
import torch

from dualscale.formats.model import VERSION

from .model import load_model
from .unet import MULTIPLE, PropagationUNet, map_slices

OPSET = 17
SOURCE_KEY = "dualscale:source_sha256"  # ONNX metadata: SHA-256 (hex) of the model file exported


def export_onnx(model: PropagationUNet, path: str | Path, half: bool = False, meta: dict | None = None) -> Path:
    """Write ``model`` as ONNX (legacy TorchScript exporter, opset 17; no onnxscript needed),
    atomically (a temporary file renamed into place)."""
    from dualscale.formats.atomic import atomic_path

    with atomic_path(path) as tmp:
        _export_onnx(model, tmp, half, meta)
    return Path(path)


def _export_onnx(model: PropagationUNet, path: Path, half: bool, meta: dict | None) -> None:
    import onnx

    m = copy.deepcopy(model).eval().cpu()  # never round the caller's weights
    m = m.half() if half else m.float()
    dtype = torch.float16 if half else torch.float32
    dummy = torch.rand(1, m.config.in_channels, 4 * MULTIPLE, 4 * MULTIPLE, dtype=dtype)
    with warnings.catch_warnings():  # GroupNorm's batch-size check is a harmless trace constant
        warnings.simplefilter("ignore")
        torch.onnx.export(m, (dummy,), str(path), input_names=["image"], output_names=["maps"],
                          opset_version=OPSET, dynamo=False,
                          dynamic_axes={"image": {0: "n", 2: "h", 3: "w"}, "maps": {0: "n", 2: "h", 3: "w"}})
    proto = onnx.load(str(path))
    info = {"dualscale:maps": json.dumps(list(m.config.maps)),
            "dualscale:channels": json.dumps({k: [s.start, s.stop] for k, s in map_slices(m.config.maps).items()}),
            "dualscale:precision": "fp16" if half else "fp32", "dualscale:multiple": str(MULTIPLE),
            "dualscale:version": str(VERSION)}
    for k, v in {**info, **(meta or {})}.items():
        e = proto.metadata_props.add()
        e.key, e.value = k, str(v)
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))


OPTIMIZATION_LEVELS = ("all", "extended", "basic", "none")


def session(path: str | Path, threads: int | None = None, optimization: str = "all", profile: str | None = None):
    """An onnxruntime CPU session (CUDA first when available).

    ``threads``: intra-op threads (``None``: onnxruntime's default, one per core); no
    busy-waiting (spinning threads starve each other on shared cores).  ``optimization``: graph
    optimisation level, ``"all"`` (default: constant folding, node fusions and, on x86, the
    NCHWc blocked layout for convolutions), ``"extended"`` (fusions, no layout change),
    ``"basic"`` or ``"none"``; measured in docs/PROPAGATION.md.  ``profile``: a file prefix
    for onnxruntime's per-node profile (``enable_profiling``; ``session.end_profiling()``
    writes it).
    """
    import onnxruntime as ort

    levels = {"all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
              "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
              "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
              "none": ort.GraphOptimizationLevel.ORT_DISABLE_ALL}
    if optimization not in levels:
        raise ValueError(f"optimization must be one of {', '.join(levels)}, got {optimization!r}")
    so = ort.SessionOptions()
    if threads:
        so.intra_op_num_threads = threads
    so.graph_optimization_level = levels[optimization]
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if profile:
        so.enable_profiling = True
        so.profile_file_prefix = str(profile)
    prov = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()]
    return ort.InferenceSession(str(path), so, providers=prov)


def parity(model: PropagationUNet, onnx_path: str | Path, size: int = 64, batch: int = 2,
           seed: int = 0) -> dict[str, float]:
    """Max absolute difference ONNX vs PyTorch fp32, per map, on random radiance in [0, 2)."""
    sess = session(onnx_path)
    inp = sess.get_inputs()[0]
    half = inp.type == "tensor(float16)"
    x = 2 * torch.rand(batch, model.config.in_channels, size, size, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        ref = model.eval().float()(x).numpy()
    got = sess.run(None, {inp.name: x.numpy().astype(np.float16 if half else np.float32)})[0].astype(np.float32)
    return {k: float(np.abs(got[:, s] - ref[:, s]).max()) for k, s in map_slices(model.config.maps).items()}


def onnx_paths(model_path: str | Path) -> tuple[Path, Path]:
    """``(fp32, fp16)`` ONNX files written next to a model file by :func:`export_model`."""
    p = Path(model_path)
    return p.with_suffix(".onnx"), p.with_suffix(".fp16.onnx")


def onnx_path(model_path: str | Path, precision: str) -> Path:
    """The ONNX file of ``precision`` (``fp32``, ``fp16``, ``int8``) next to a model file."""
    p = Path(model_path)
    suffix = {"fp32": ".onnx", "fp16": ".fp16.onnx", "int8": ".int8.onnx"}.get(precision)
    if suffix is None:
        raise ValueError(f"precision must be fp32, fp16 or int8, got {precision!r}")
    return p.with_suffix(suffix)


def quantize_int8(fp32_path: str | Path, path: str | Path) -> Path:
    """Dynamic int8 quantisation of an fp32 export (``quantize_dynamic``, uint8 weights: int8
    weights ran ~6x slower in onnxruntime's ``ConvInteger`` here), written atomically.  The
    metadata say ``dualscale:precision`` = ``int8`` and record the fp32 file's name and SHA-256
    (``dualscale:quantised_from[_sha256]``), so a stale int8 file is refused when opened
    (:meth:`dualscale.propagate.infer.OnnxModel.open`)."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    from dualscale.formats.atomic import atomic_path

    fp32_path = Path(fp32_path)
    digest = hashlib.sha256(fp32_path.read_bytes()).hexdigest()
    with atomic_path(path) as tmp:
        logging.disable(logging.WARNING)  # its advice to pre-process: measured, gives the same graph here
        try:
            quantize_dynamic(str(fp32_path), str(tmp), weight_type=QuantType.QUInt8)
        finally:
            logging.disable(logging.NOTSET)
        proto = onnx.load(str(tmp))
        props = {e.key: e.value for e in proto.metadata_props if e.key != "onnx.infer"}
        if props.get("dualscale:precision") != "fp32":
            raise ValueError(f"{fp32_path}: not an fp32 dualscale export (precision "
                             f"{props.get('dualscale:precision')!r})")
        props.update({"dualscale:precision": "int8", "dualscale:quantised_from": fp32_path.name,
                      "dualscale:quantised_from_sha256": digest})
        del proto.metadata_props[:]
        for k, v in props.items():
            e = proto.metadata_props.add()
            e.key, e.value = k, v
        onnx.save(proto, str(tmp))
    return Path(path)


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def recorded_source(onnx_file: str | Path) -> str | None:
    """The model-file SHA-256 that an ONNX export records (:data:`SOURCE_KEY`), or ``None`` when
    the file is missing, not a readable ONNX model, or records none (an export made before
    the hash was recorded)."""
    import onnx

    try:
        proto = onnx.load(str(onnx_file), load_external_data=False)
    except Exception:  # noqa: BLE001 -- missing, truncated, not ONNX: all mean "export again"
        return None
    return next((e.value for e in proto.metadata_props if e.key == SOURCE_KEY), None)


def exports_current(model_path: str | Path, digest: str | None = None) -> bool:
    """Whether both ONNX exports next to ``model_path`` (:func:`onnx_paths`) were made from a
    model file with the content it has now: each records ``digest`` (default: the file's
    SHA-256, :func:`file_sha256`).  Modification times play no part."""
    digest = digest or file_sha256(model_path)
    return all(recorded_source(p) == digest for p in onnx_paths(model_path))


def ensure_exported(model_path: str | Path, check: bool = True) -> dict | None:
    """Export ``model_path`` to fp32 and fp16 ONNX (:func:`export_model`) unless both exports
    beside it were made from the same content (:func:`exports_current`).  Returns
    :func:`export_model`'s dict when it exported (with parity when ``check``), ``None`` when
    the exports were current.  The one re-export decision of ``dualscale propagate run`` and of
    the propagate stage."""
    digest = file_sha256(model_path)
    if exports_current(model_path, digest):
        return None
    return export_model(model_path, check=check, digest=digest)


def export_model(model_path: str | Path, check: bool = True, int8: bool = False, digest: str | None = None) -> dict:
    """Export a model file to fp32 and fp16 ONNX next to it (and int8 with ``int8=True``:
    :func:`quantize_int8`); returns paths and parity per map (max abs difference against
    PyTorch fp32, :func:`parity`).  Each export records the model file's SHA-256
    (:data:`SOURCE_KEY`; ``digest``: that hash when the caller has it, taken before the file is
    read, so a file replaced meanwhile is exported again next time)."""
    digest = digest or file_sha256(model_path)
    model, doc = load_model(model_path)
    meta = {"dualscale:input_reference": json.dumps(doc.get("input_reference")), SOURCE_KEY: digest}
    p32, p16 = onnx_paths(model_path)
    export_onnx(model, p32, half=False, meta=meta)
    export_onnx(model, p16, half=True, meta=meta)
    out: dict = {"fp32": str(p32), "fp16": str(p16)}
    if int8:
        out["int8"] = str(quantize_int8(p32, onnx_path(model_path, "int8")))
    if check:
        out["parity_fp32"] = parity(model, p32)
        out["parity_fp16"] = parity(model, p16)
        if int8:
            out["parity_int8"] = parity(model, out["int8"])
    return out
