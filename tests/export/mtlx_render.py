"""Render a MaterialX export with MaterialX's own GLSL renderer (``PyMaterialXRenderGlsl``, PyPI
``materialx`` 1.39.5), as a user's MaterialX viewer would, for the export tests and
bench/bench_export.py (issue 28).

:func:`render` draws the swatch as a flat quad seen from the zenith by an orthographic camera,
one pixel per texel, lit by one ``directional_light`` of colour 1 and intensity 1, and returns
the framebuffer as linear radiance ``(H, W, 3)`` float64, rows **top first** (like our maps), in
units of ``f cos`` [1/sr], i.e. directly comparable with :func:`dualscale.bsdf.model.evaluate`
for the same light and view ``(0, 0, 1)``.  Frame: the quad lies in the xy plane, +x = image
right = +u, +y = image up = +v, +z = out of the sample (our macro frame); texture coordinate
(0, 0) is the image's lower-left (MaterialX's convention, ``fileTextureVerticalFlip``).

What it takes to make the renderer work here (found for issue 28; docs/EXPORT.md):

1. A GL context: Xvfb (Debian ``xvfb``, ``xauth``) with Mesa's llvmpipe.  :func:`available`
   starts one X server per process (``DISPLAY`` is set), and says why not when it cannot.
2. ``SPECULAR_ENVIRONMENT_NONE`` generates GLSL that does not compile in 1.39.5
   (``u_refractionTwoSided`` undeclared), so the shader uses FIS with *black* radiance and
   irradiance maps: the environment contributes nothing, only the directional light lights.
3. The image loader (``MaterialX/_scripts/oiio_loader.py``, OpenImageIO: it reads the EXR data
   textures, which the built-in stb loader cannot) is a Python subclass: a reference to it must
   be kept for as long as the renderer lives, or C++ calls a destroyed object ("pure virtual").
4. The loader must be wrapped in ``GLTextureHandler``: a plain ``ImageHandler`` uploads nothing
   and every texture reads as zero.
5. ``captureImage`` needs an ``Image`` argument (``captureImage(None)`` fails), and the
   framebuffer's rows come bottom-up: they are flipped here.
6. ``GLTextureHandler`` sets a maximum anisotropy of 16, and llvmpipe's anisotropic filter then
   blurs even a texture drawn one texel per pixel (a lone bright texel keeps about half its
   value at its own centre, whatever ``filtertype`` says).  :func:`available` therefore sets
   ``MESA_EXTENSION_OVERRIDE`` to hide ``GL_{EXT,ARB}_texture_filter_anisotropic`` before the first
   context: textures then filter bilinearly (a random-albedo diffuse swatch matches to 0.2 %),
   and MaterialX's refused ``glTexParameterf`` (``GL_INVALID_ENUM``, 1280) is dropped from its
   console output here.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

SHADERS = ("standard_surface", "open_pbr_surface")

_XVFB: subprocess.Popen | None = None
_WHY_NOT: str | None = None

# a unit quad [-1, 1]^2 in the xy plane, normal +z, uv (0, 0) at the lower-left
_QUAD_OBJ = """v -1 -1 0
v 1 -1 0
v 1 1 0
v -1 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
f 1/1/1 2/2/1 3/3/1
f 1/1/1 3/3/1 4/4/1
"""


def available() -> str | None:
    """``None`` when a GL context can be made (starting Xvfb on a free display if ``DISPLAY`` is
    unset), else the reason why not (for ``pytest.skip``).  Cached per process."""
    global _WHY_NOT
    if _WHY_NOT is None and not _PROBED:
        try:
            import MaterialX.PyMaterialXRenderGlsl  # noqa: F401
            import OpenImageIO  # noqa: F401
        except ImportError as e:
            _WHY_NOT = f"MaterialX's GLSL renderer or OpenImageIO is not importable: {e}"
            return _WHY_NOT
        no_aniso = "-GL_EXT_texture_filter_anisotropic -GL_ARB_texture_filter_anisotropic"
        os.environ["MESA_EXTENSION_OVERRIDE"] = f"{os.environ.get('MESA_EXTENSION_OVERRIDE', '')} {no_aniso}".strip()
        _WHY_NOT = _start_display() or _probe()
    return _WHY_NOT


_GL_ANISO_NOISE = "OpenGL error after program bind"


@contextlib.contextmanager
def _console_filtered():
    """Run with the process's stdout/stderr (fds 1, 2) caught; re-emit all but the
    ``GL_INVALID_ENUM`` lines that hiding the anisotropy extension makes MaterialX print."""
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile("w+b") as tmp:
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            tmp.seek(0)
            keep = [ln for ln in tmp.read().decode(errors="replace").splitlines()
                    if not (ln.startswith(_GL_ANISO_NOISE) and ln.rstrip().endswith(": 1280"))]
            if keep:
                print("\n".join(keep), file=sys.stderr)


_PROBED = False


def _probe() -> str | None:
    """Make a 4 x 4 GLSL renderer in a child process (a display that cannot be opened ends the
    process, with no exception to catch): the GL context works, or why not."""
    global _PROBED
    _PROBED = True
    import sys

    code = ("import MaterialX.PyMaterialXRender as r, MaterialX.PyMaterialXRenderGlsl as g; "
            "g.GlslRenderer.create(4, 4, r.BaseType.FLOAT).initialize()")
    try:
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return "MaterialX's GLSL renderer did not initialise within 60 s"
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [f"exit status {proc.returncode}"]
        return f"no OpenGL context for MaterialX's GLSL renderer on DISPLAY={os.environ.get('DISPLAY')}: {tail[0]}"
    return None


def _start_display() -> str | None:
    """Start Xvfb on the first free display :90..:119 unless ``DISPLAY`` is set; why not, or None."""
    global _XVFB
    if os.environ.get("DISPLAY"):
        return None
    exe = shutil.which("Xvfb")
    if exe is None:
        return "Xvfb is not installed (`make apt` installs Debian's xvfb and xauth)"
    for disp in range(90, 120):
        if Path(f"/tmp/.X{disp}-lock").exists():
            continue
        proc = subprocess.Popen([exe, f":{disp}", "-screen", "0", "640x480x24", "-nolisten", "tcp"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for _ in range(50):
            if Path(f"/tmp/.X11-unix/X{disp}").exists() or proc.poll() is not None:
                break
            time.sleep(0.1)
        if proc.poll() is None:
            _XVFB = proc
            os.environ["DISPLAY"] = f":{disp}"
            import atexit

            atexit.register(proc.terminate)
            return None
    return "Xvfb did not start on any display :90-:119"


def _black_image():
    import MaterialX as mx
    import MaterialX.PyMaterialXRender as mx_render

    return mx_render.createUniformImage(4, 2, 3, mx_render.BaseType.FLOAT, mx.Color4(0, 0, 0, 1))


class MtlxRenderer:
    """One GLSL renderer of ``size`` ``(W, H)`` pixels for one exported document (the ``.mtlx``
    path; its textures beside it).  :meth:`render` ``(shader, light)`` -> ``(H, W, 3)``.
    Raises ``RuntimeError`` with MaterialX's message when a shader does not compile or link."""

    def __init__(self, mtlx_path: str | Path, size: tuple[int, int]) -> None:
        import MaterialX as mx
        import MaterialX.PyMaterialXGenGlsl as mx_glsl
        import MaterialX.PyMaterialXGenShader as mx_gen
        import MaterialX.PyMaterialXRender as mx_render
        import MaterialX.PyMaterialXRenderGlsl as mx_rglsl
        # workaround 3: MaterialX's own OpenImageIO loader; it configures logging at INFO on import
        from MaterialX._scripts.oiio_loader import OiioImageLoader

        logging.getLogger("OIIOLoad").setLevel(logging.WARNING)
        why = available()
        if why:
            raise RuntimeError(why)
        self.path = Path(mtlx_path)
        self.size = (int(size[0]), int(size[1]))
        self._mx, self._gen_mod, self._render_mod = mx, mx_gen, mx_render
        self.stdlib = mx.createDocument()
        mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), self.stdlib)
        self.doc = mx.createDocument()
        mx.readFromXmlFile(self.doc, str(self.path))
        self.doc.setDataLibrary(self.stdlib)

        self.gen = mx_glsl.GlslShaderGenerator.create()
        self.ctx = mx_gen.GenContext(self.gen)
        self.ctx.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
        cms = mx_gen.DefaultColorManagementSystem.create(self.gen.getTarget())
        cms.loadLibrary(self.stdlib)
        self.gen.setColorManagementSystem(cms)  # srgb_texture -> lin_rec709 on the GPU
        opts = self.ctx.getOptions()
        opts.fileTextureVerticalFlip = True  # image rows top first, uv (0, 0) at the lower-left
        opts.hwSpecularEnvironmentMethod = mx_gen.SPECULAR_ENVIRONMENT_FIS  # workaround 2
        opts.hwSrgbEncodeOutput = False  # linear radiance out
        opts.hwTransparency = False
        opts.hwMaxActiveLightSources = 1
        opts.hwShadowMap = False
        opts.hwAmbientOcclusion = False

        w, h = self.size
        self.renderer = mx_rglsl.GlslRenderer.create(w, h, mx_render.BaseType.FLOAT)
        self.renderer.initialize()
        self.loader = OiioImageLoader()  # workaround 3: this reference keeps the Python object alive
        self.images = mx_rglsl.GLTextureHandler.create(self.loader)  # workaround 4
        self.images.setSearchPath(mx.FileSearchPath(str(self.path.parent)))
        self.renderer.setImageHandler(self.images)

        with tempfile.TemporaryDirectory() as tmp:
            obj = Path(tmp) / "quad.obj"
            obj.write_text(_QUAD_OBJ)
            geom = mx_render.GeometryHandler.create()
            geom.addLoader(mx_render.TinyObjLoader.create())
            if not geom.loadGeometry(mx.FilePath(str(obj)), False):
                raise RuntimeError("MaterialX could not load the quad mesh")
        self.renderer.setGeometryHandler(geom)

        cam = self.renderer.getCamera()
        cam.setWorldMatrix(mx.Matrix44.IDENTITY)
        cam.setViewMatrix(mx_render.Camera.createViewMatrix(mx.Vector3(0, 0, 5), mx.Vector3(0, 0, 0),
                                                           mx.Vector3(0, 1, 0)))
        cam.setProjectionMatrix(mx_render.Camera.createOrthographicMatrix(-1, 1, -1, 1, 0.1, 10))
        cam.setViewportSize(mx.Vector2(w, h))

        self.lights = mx_render.LightHandler.create()
        self.lights.setEnvRadianceMap(_black_image())  # workaround 2: FIS with a black environment
        self.lights.setEnvIrradianceMap(_black_image())
        self.lights.setIndirectLighting(False)
        self.renderer.setLightHandler(self.lights)
        self._light_doc = None

    def _set_light(self, light: np.ndarray) -> None:
        """One ``directional_light`` towards ``light`` (unit (3,), macro frame, pointing to the
        light): MaterialX's ``direction`` is the way the light travels, ``-light``."""
        mx = self._mx
        ldoc = mx.createDocument()
        ldoc.setDataLibrary(self.stdlib)
        node = ldoc.addNode("directional_light", "sun", "lightshader")
        d = -np.asarray(light, np.float64)
        node.setInputValue("direction", mx.Vector3(*map(float, d)))
        node.setInputValue("color", mx.Color3(1.0, 1.0, 1.0))
        node.setInputValue("intensity", 1.0)
        self.lights.setLightSources([node])
        self.lights.registerLights(ldoc, [node], self.ctx)
        self._light_doc = ldoc  # the node must outlive the render

    def render(self, shader: str, light: np.ndarray) -> np.ndarray:
        """Radiance ``(H, W, 3)`` float64, rows top first, of the export's ``shader``
        (``"standard_surface"`` or ``"open_pbr_surface"``) lit from ``light``."""
        mx, mx_gen, mx_render = self._mx, self._gen_mod, self._render_mod
        if shader not in SHADERS:
            raise ValueError(f"shader must be one of {SHADERS}, not {shader!r}")
        self._set_light(light)
        nodes = [n for n in self.doc.getNodes() if n.getCategory() == shader]
        if len(nodes) != 1:
            raise RuntimeError(f"{self.path.name}: expected one {shader} node, found {len(nodes)}")
        elem = nodes[0]
        hw = self.gen.generate(elem.getName(), elem, self.ctx)
        try:
            self.renderer.createProgram(hw)
            self.renderer.validateInputs()
        except Exception as e:  # ExceptionRenderError reaches Python as LookupError, with the GL log
            log = "; ".join(getattr(e, "errorLog", []) or [])
            raise RuntimeError(f"MaterialX GLSL {shader}: {e} {log}".strip()) from e
        with _console_filtered():
            self.renderer.render()
        w, h = self.size
        img = mx_render.Image.create(w, h, 4, mx_render.BaseType.FLOAT)
        img.createResourceBuffer()
        img = self.renderer.captureImage(img)  # workaround 5: an Image argument
        buf = (ctypes.c_float * (w * h * 4)).from_address(img.getResourceBuffer())
        px = np.frombuffer(buf, np.float32).reshape(h, w, 4)[::-1, :, :3]  # rows bottom-up -> top first
        return px.astype(np.float64)


def sun(elevation_deg: float, azimuth_deg: float = 0.0) -> np.ndarray:
    """Unit direction towards a light at ``elevation_deg`` above the sample plane and
    ``azimuth_deg`` CCW from +x (image right), macro frame ``(3,)``."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
