"""``dualscale synth`` and ``dualscale render``: synthetic ground truth and rendering to EXR.

:func:`register` adds both to the ``dualscale`` parser; each subcommand sets ``fn`` (called
with the parsed namespace, returns an exit code; errors are raised, see :mod:`dualscale.errors`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from dualscale.errors import FormatError, InputError
from dualscale.progress import tracker
from dualscale.protocol import regmap

from .choices import MATERIALS
from .common import add_output, add_work_options, apply_threads, output_folder, want_progress

if TYPE_CHECKING:
    import torch


def _analyzers(text: str | None, option: str = "--analyzer") -> list[float | None]:
    """The analyser angles of ``option`` (comma-separated degrees, or ``none``); anything else,
    an angle given twice included, is one line naming the option (``InputError``, exit 2)."""
    import math

    if text is None or text == "none":
        return [None]
    out: list[float | None] = []
    for x in text.split(","):
        try:
            a = float(x)
        except ValueError:
            a = math.nan
        if not math.isfinite(a):
            raise InputError(f"{option} {text}: {x.strip()!r} is not an angle in degrees; give comma-separated "
                             "angles (e.g. 0,90) or 'none'")
        out.append(a)
    if len(set(out)) != len(out):
        raise InputError(f"{option} {text}: an angle is given twice")
    return out


def _write_capture(writer, img: torch.Tensor, cam, png_dir: Path | None, kind: str, lid: int | None, direction,
                   analyzer: float | None, relative: bool, exposure_s: float) -> None:
    from dualscale.formats.exr import write_png_preview

    rec = writer.add(img.detach().cpu().numpy(), cam, kind, lid, direction, 1.0, analyzer, relative, exposure_s)
    if png_dir is not None:
        write_png_preview(png_dir / (Path(rec.file).stem + ".png"), img.detach().cpu().numpy())


def _capture_set(maps, cam, out: Path, lights: list[tuple[str, int | None]], analyzers: list[float | None],
                 relative: bool, texel_mm: float | None, realistic: bool, previews: bool, extra: dict,
                 geometry=None, progress=None) -> Path:
    """Render one image per light x analyser into a dataset at ``out``: relative radiance, or,
    with ``realistic``, camera counts as the virtual rig's sensor takes them (metered exposure per
    image, the rig's LED spectra, gains, vignetting, dark signal, noise;
    :func:`dualscale.sim.targets.capture_material`), which the calibration of the same virtual rig
    (``synth-targets`` + ``calibrate``) turns back into radiance.  ``progress`` as in
    :mod:`dualscale.progress` (one unit per image)."""
    import numpy as np
    import torch

    from dualscale.formats.dataset import DatasetWriter
    from dualscale.geometry.dome import DomeGeometry
    from dualscale.sim.render import Analyzer, LightRealism, LightState, render
    from dualscale.sim.targets import SynthConfig, capture_material, rig_exposer, rig_record

    dome = DomeGeometry.from_regmap()
    units = "dn_normalized" if realistic else "relative_radiance"
    space = f"camera_raw:{SynthConfig().sens(cam.name)}" if realistic else "linear_rec709"
    png_dir = out / "previews" if previews else None
    exposer = rig_exposer(cam) if realistic else None
    exposures: list[float] = []
    with DatasetWriter(out, units=units, colour_space=space, extra=extra, rig=rig_record() if realistic else None,
                       dome={"source": dome.source, "polarizer": dome.polarizer, "radius_mm": dome.radius_mm}) as w, \
            tracker(progress, len(lights) * len(analyzers), f"render {out.name}", "image") as bar:
        for kind, lid in lights:
            state = {"led": LightState.led, "backlight": LightState.backlight}[kind](lid) if kind != "diffuse" \
                else LightState.diffuse_group()
            direction = [float(x) for x in dome.led_dirs[lid]] if kind == "led" else None
            for a in analyzers:
                an = None if a is None or not cam.has_analyzer else Analyzer(a, relative)
                img = render(maps, cam, state, dome, an, texel_mm=texel_mm, geometry=geometry,
                             realism=LightRealism(shadows=geometry is not None))
                exposure_s = 1.0
                if realistic:
                    dn, exposure_s = capture_material(img.detach().double().cpu().numpy(), exposer, kind, lid)
                    exposures.append(exposure_s)
                    img = torch.from_numpy(dn.astype("float32"))
                _write_capture(w, img, cam, png_dir, kind, lid, direction, None if an is None else a,
                               relative and an is not None, exposure_s)
                bar.update(what=f"{kind} {'' if lid is None else lid}".strip())
        if realistic:  # dark frames at the shortest and longest exposure, as the rig takes them
            for t in sorted({min(exposures), max(exposures)}):
                dark = exposer(np.zeros((cam.height, cam.width, 3)), t).astype(np.float32)
                w.add(dark, cam, "off", None, None, 1.0, None, False, t)
    return out / "manifest.json"


#: the largest map or image side synth and render make (texels): 8192^2 maps already take several GB
MAX_SIZE = 8192
#: the smallest (the synthetic materials' weave needs it)
MIN_SIZE = 8
#: physical sizes (texel in um, field in mm) beyond which the virtual rig's geometry means nothing
MAX_TEXEL_UM = 1e5
MAX_FIELD_MM = 1e4


def _check_size(value: int | None, option: str) -> None:
    if value is not None and not MIN_SIZE <= value <= MAX_SIZE:
        raise InputError(f"{option} {value}: choose {MIN_SIZE}..{MAX_SIZE} texels (a side of {value} would need "
                         f"{_gib(value):.3g} GiB for the maps alone)" if value > MAX_SIZE else
                         f"{option} {value}: choose {MIN_SIZE}..{MAX_SIZE} texels")


def _gib(side: int) -> float:
    """Memory of one set of float32 maps of ``side``^2 texels (17 channels), in GiB."""
    return side * side * 17 * 4 / 2**30


def _check_length(value: float | None, option: str, top: float, unit: str) -> None:
    import math

    if value is not None and not (math.isfinite(value) and 0 < value <= top):
        raise InputError(f"{option} {value:g}: must be a positive, finite number of {unit} (at most {top:g})")


def check_synth_args(args: argparse.Namespace) -> None:
    """Refuse, before any folder is made, the sizes ``synth`` cannot make (one line, exit 2):
    a side outside :data:`MIN_SIZE`..:data:`MAX_SIZE` (``--size 1000000`` would be 7 TiB), a
    texel or field that is not a positive finite length (``--mid-field-mm inf``)."""
    _check_size(args.size, "--size")
    _check_length(args.texel_um, "--texel-um", MAX_TEXEL_UM, "micrometres")
    if not 0 <= args.seed < 2**63:
        raise InputError(f"--seed {args.seed}: choose a whole number 0..{2**63 - 1}")
    _leds(args.lights)
    _analyzers(args.analyzers, "--analyzers")
    if args.mid:
        _check_size(args.mid_size, "--mid-size")
        _check_length(args.mid_field_mm, "--mid-field-mm", MAX_FIELD_MM, "mm")


def synth_identity(args: argparse.Namespace) -> list[str]:
    """What identifies a ``synth`` run in its folder's record: every option that changes its
    outputs (a rerun with other ones is another run, refused unless ``--overwrite``, so that 32^2
    maps never lie beside a 64^2 dataset; issue 24 trial)."""
    ident = [f"material:{args.material}", f"seed:{args.seed}", f"size:{args.size}", f"texel_um:{args.texel_um:g}",
             f"previews:{not args.no_previews}"]
    if args.dataset:
        ans = _analyzers(args.analyzers, "--analyzers")
        ident.append(f"dataset:lights={args.lights},analyzers={','.join('none' if a is None else f'{a:g}' for a in ans)},"
                     f"shadows={bool(args.shadows)}")
    if args.mid:
        ident.append(f"mid:size={args.mid_size},field_mm={args.mid_field_mm:g}")
    if args.dataset or args.mid:
        ident.append(f"realistic:{bool(args.realistic)}")
    return ident


#: synth's memory, calibrated with ``/usr/bin/time -v`` (peak RSS) of ``synth twill`` at 256..1024
#: texels: the interpreter with torch/numpy/OpenImageIO loaded, then per texel of a side^2 material
#: its generation and saving (the rendering of ``--dataset`` streams image by image, under it;
#: the number of lights does not change the peak); the micro maps stay loaded while ``--mid``'s
#: image is made, whose diffuse-group render takes far more per pixel (``--size 512 --mid
#: --mid-size 1024``: 3.9 GB).  Rounded up (1024: 0.70 GB measured, 0.73 GB estimated).
MEM_BASE = 350 * 2**20
MEM_PER_TEXEL = 400
MEM_MID_PER_PIXEL = 3600
MEM_KEPT_PER_TEXEL = 17 * 4 + 3 * 8  # the float32 maps, and one float64 image of --dataset


def synth_memory(args: argparse.Namespace) -> int:
    """The estimated peak memory (bytes) of ``synth`` with ``args`` (:data:`MEM_PER_TEXEL`)."""
    micro = MEM_PER_TEXEL * args.size ** 2
    if args.mid:
        micro = max(micro, MEM_KEPT_PER_TEXEL * args.size ** 2 + MEM_MID_PER_PIXEL * args.mid_size ** 2)
    return MEM_BASE + micro


def _check_memory(args: argparse.Namespace) -> None:
    """Refuse, before any work (exit 2), a ``synth`` whose estimated memory (:func:`synth_memory`)
    exceeds what this machine has available (``MemAvailable``) or the process may use (``ulimit
    -v``); the message names the option, the estimate and the largest side that fits.  It used to
    be killed by the kernel's OOM killer (exit 137) or to fail with a ``MemoryError``."""
    import math

    from dualscale.cli import available_memory, memory_text

    args.memory_hint = "use a smaller --size or --mid-size"
    need = synth_memory(args)
    avail, limit = available_memory()
    room = min(avail, limit) if limit is not None else avail
    if avail <= 0 or need <= room:
        return
    mid_big = args.mid and MEM_MID_PER_PIXEL * args.mid_size ** 2 > MEM_PER_TEXEL * args.size ** 2
    option, side, per = ("--mid-size", args.mid_size, MEM_MID_PER_PIXEL) if mid_big else \
        ("--size", args.size, MEM_PER_TEXEL)
    other = MEM_KEPT_PER_TEXEL * args.size ** 2 if mid_big else 0
    fits = int(math.sqrt(max(room - MEM_BASE - other, 0) / per)) // 64 * 64
    advice = f"choose {option} {fits} or less" if fits >= MIN_SIZE else "free memory first"
    raise InputError(f"{option} {side}: synth would need about {need / 2**30:.1f} GiB of memory and "
                     f"{memory_text()}; {advice}")


def cmd_synth(args: argparse.Namespace) -> int:
    check_synth_args(args)
    _check_memory(args)
    apply_threads(args)
    progress = want_progress(args)
    out = Path(args.output)
    texel = args.texel_um / 1000.0
    leds = _leds(args.lights)
    with output_folder(args, "synth", synth_identity(args)):
        return _synth(args, out, texel, leds, progress)


def _synth(args: argparse.Namespace, out: Path, texel: float, leds, progress: bool) -> int:
    from dualscale.geometry.cameras import micro_camera, mid_camera
    from dualscale.sim.materials import generate
    from dualscale.sim.materials.io import save_material

    mat = generate(args.material, args.size, texel, args.seed)
    save_material(out / "maps", mat, previews=not args.no_previews)
    print(f"wrote ground-truth maps to {out / 'maps'}")
    if args.dataset:
        # the rig always takes the back-lit image: it is how an opaque sample shows it is opaque
        lights: list[tuple[str, int | None]] = [("led", i) for i in leds] + [("backlight", 0)]
        path = _capture_set(mat.maps, micro_camera(args.size, args.texel_um), out / "micro", lights,
                            _analyzers(args.analyzers), True, None, args.realistic, not args.no_previews,
                            {"material": mat.meta, "shadows": bool(args.shadows)},
                            mat.geometry if args.shadows else None, progress)
        print(f"wrote micro photometric dataset {path}")
    if args.mid:
        mid_texel = args.mid_field_mm / args.mid_size
        coarse = generate(args.material, args.mid_size, mid_texel, args.seed)
        cam = mid_camera(args.mid_size, field_mm=args.mid_field_mm)
        path = _capture_set(coarse.maps, cam, out / "mid", [("diffuse", None)], [None], False, mid_texel, args.realistic,
                            not args.no_previews, {"material": coarse.meta}, progress=progress)
        print(f"wrote mid-range guidance image {path}")
    return 0


def _leds(spec: str) -> range:
    """``all`` or ``modN`` (every N-th LED)."""
    if spec == "all":
        return range(regmap.N_LEDS)
    step = spec[3:]
    if not spec.startswith("mod") or not step.isdigit() or int(step) < 1:
        raise InputError(f"--lights {spec!r}: use 'all' or 'modN' (every N-th LED, N >= 1)")
    return range(0, regmap.N_LEDS, int(step))


def _shadow_geometry(args: argparse.Namespace, shape: tuple[int, int]):
    """The relief saved beside the maps, checked against the micro camera it will shade."""
    from dualscale.formats.relief import load_geometry

    path = Path(args.maps) / "geometry.exr"
    if args.camera != "micro":
        raise InputError("--shadows works on the map grid only: use --camera micro")
    if not path.is_file():
        raise FormatError(f"--shadows needs the relief {path} (written by 'dualscale synth')")
    geom = load_geometry(path)
    if geom.shape != tuple(shape):
        raise FormatError(f"{path} is {geom.shape}, the maps are {tuple(shape)}")
    if abs(geom.texel_mm * 1000.0 - args.texel_um) > 1e-6 * args.texel_um:
        raise InputError(f"--texel-um {args.texel_um} does not match the relief's {geom.texel_mm * 1000.0:g} um "
                         f"({path})")
    return geom


def _render_lights(args: argparse.Namespace) -> list[tuple[str, int | None]]:
    """The lights asked for, checked against the register map."""
    lights: list[tuple[str, int | None]] = [("led", i) for i in args.led or []]
    lights += [("backlight", i) for i in args.backlight or []]
    if args.diffuse:
        lights.append(("diffuse", None))
    if not lights:
        raise InputError("choose at least one light: --led ID, --backlight ID or --diffuse")
    for opt, kind in (("--led", "led"), ("--backlight", "backlight")):
        ids = [i for k, i in lights if k == kind]
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if twice:
            raise InputError(f"{opt}: {'id' if len(twice) == 1 else 'ids'} {', '.join(map(str, twice))} given twice "
                             "(one image each)")
    bad = [i for k, i in lights if k == "led" and not 0 <= i < regmap.N_LEDS]
    if bad:
        raise InputError(f"--led: LED ids out of range 0..{regmap.N_LEDS - 1}: {bad}")
    bad = [i for k, i in lights if k == "backlight" and not 0 <= i < regmap.N_BACKLIGHTS]
    if bad:
        raise InputError(f"--backlight: ids out of range 0..{regmap.N_BACKLIGHTS - 1}: {bad}")
    return lights


def cmd_render(args: argparse.Namespace) -> int:
    import torch

    from dualscale.geometry.cameras import micro_camera, mid_camera, polar_camera
    from dualscale.formats.maps import load_maps

    _check_size(args.size, "--size")
    _check_length(args.texel_um, "--texel-um", MAX_TEXEL_UM, "micrometres")
    lights = _render_lights(args)
    analyzers = _analyzers(args.analyzer)  # every option is checked before the maps are read
    apply_threads(args)
    maps, meta = load_maps(args.maps, dtype=torch.float64 if args.float64 else torch.float32)
    h, w = maps.shape
    if args.camera == "micro":
        if h != w:
            raise InputError(f"{args.maps}: the micro camera needs square maps, these are {h}x{w}")
        cam = micro_camera(w, args.texel_um)
        texel = None
    else:
        size = args.size or 512
        cam = mid_camera(size) if args.camera == "mid" else polar_camera(int(args.camera[-1]), size)
        texel = args.texel_um / 1000.0
    if not cam.has_analyzer and analyzers != [None]:
        raise InputError(f"--analyzer {args.analyzer}: the {args.camera} camera has no analyser (the micro and polar "
                         "cameras have one); drop --analyzer, or give --analyzer none")
    geometry = _shadow_geometry(args, maps.shape) if args.shadows else None
    with output_folder(args, "render", [args.maps]):
        path = _capture_set(maps, cam, Path(args.output), lights, analyzers, args.relative, texel,
                            args.realistic, True, {"maps": str(args.maps), "material": meta,
                                                   "shadows": bool(args.shadows)}, geometry, want_progress(args))
    print(f"wrote {path}")
    return 0


def register(subparsers) -> None:
    """Add ``synth`` and ``render`` to an ``argparse`` subparsers object."""
    p = subparsers.add_parser("synth", help="write ground-truth maps (and optionally captures) of a synthetic material")
    p.add_argument("material", choices=sorted(MATERIALS))
    add_output(p, "output directory (maps/, micro/, mid/)")
    p.add_argument("--size", type=int, default=512,
                   help=f"map size in texels (square, {MIN_SIZE}..{MAX_SIZE}; default: 512)")
    p.add_argument("--texel-um", type=float, default=1.8, help="texel (= micro pixel) size in micrometres (default: 1.8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic material (default: 0)")
    p.add_argument("--dataset", action="store_true", help="also render a micro photometric dataset")
    p.add_argument("--lights", default="all", help="'all' or 'modN' (every N-th LED; default: all)")
    p.add_argument("--analyzers", default="0,90", help="analyser angles relative to each LED polariser, or 'none' (default: 0,90)")
    p.add_argument("--mid", action="store_true", help="also render a mid-range guidance image (diffuse group)")
    p.add_argument("--mid-size", type=int, default=256,
                   help=f"side of the mid-range guidance image in pixels ({MIN_SIZE}..{MAX_SIZE}; default: 256)")
    p.add_argument("--mid-field-mm", type=float, default=100.0,
                   help="field of the mid-range image in mm (default: 100, the rig's; smaller for a test bed)")
    p.add_argument("--realistic", action="store_true", help="capture in camera counts with the virtual rig's sensor (metered exposures, LED "
                        "spectra and gains, dark signal, noise, 12 bit); calibrate with synth-targets + calibrate")
    p.add_argument("--shadows", action="store_true",
                   help="cast shadows of the relief and of the raised fly-out fibres in the dataset")
    p.add_argument("--no-previews", action="store_true", help="write the EXR maps without PNG previews (default: previews)")
    add_work_options(p)
    p.set_defaults(fn=cmd_synth)

    r = subparsers.add_parser("render", help="render maps under chosen lights/analyser to EXR + PNG previews")
    r.add_argument("maps", help="directory written by 'synth' (its maps/ folder) or save_maps")
    add_output(r, "output dataset directory (EXR + manifest.json, previews/)")
    r.add_argument("--camera", choices=list(regmap.CAMERA_NAMES), default="micro",
                   help="the rig camera to render through (default: micro)")
    r.add_argument("--led", type=int, nargs="*", help="LED ids (one image each)")
    r.add_argument("--backlight", type=int, nargs="*", help="back-light ids")
    r.add_argument("--diffuse", action="store_true", help="also render the diffuse group")
    r.add_argument("--analyzer", default=None, help="comma-separated analyser angles [deg], or 'none'")
    r.add_argument("--relative", action="store_true", help="angles are relative to each LED polariser (0 = P0)")
    r.add_argument("--texel-um", type=float, default=1.8, help="texel size in micrometres (default: 1.8)")
    r.add_argument("--size", type=int, default=None, help="image size for mid/polar cameras")
    r.add_argument("--realistic", action="store_true", help="camera counts through the virtual sensor (gains, dark signal, noise) instead of radiance")
    r.add_argument("--float64", action="store_true", help="render in float64 (default: float32)")
    r.add_argument("--shadows", action="store_true",
                   help="cast the shadows of the relief saved with the maps (geometry.exr; micro camera only)")
    add_work_options(r)
    r.set_defaults(fn=cmd_render)
