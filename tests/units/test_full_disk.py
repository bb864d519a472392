"""A full disk while writing maps (issue 24 §7).

OpenImageIO reports success for a PNG that a full disk (or the file-size limit) cut short, so a
map or preview used to keep its final name truncated or empty.  Every image the product writes is
now checked whole before it takes its name (``formats.exr.verify_image``), and a write that runs
out of room is ``OutputError`` (exit 4, "disk full" / "File too large") with nothing under the
final name and no completion record (``material.json``, ``fit.json``) beside the missing map.

Three kinds of test, real first:

* a real full filesystem: a small tmpfs mounted in a user and mount namespace (``unshare -Urm``,
  no root needed where unprivileged user namespaces are allowed; skipped elsewhere), filled so
  that the disk runs out in the middle of a map's PNG preview;
* the kernel's file-size limit (``RLIMIT_FSIZE`` set in a child process, ``SIGXFSZ`` ignored, so
  writes past N bytes fail with ``EFBIG``), which works everywhere;
* a thin monkeypatch at the OS boundary (``os.fsync`` failing with ``ENOSPC`` or ``EIO``).
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from dualscale.errors import OutputError
from dualscale.formats import atomic
from dualscale.formats.exr import write_exr, write_png_preview

ROOT = Path(__file__).resolve().parents[2]
ENV = {k: v for k, v in os.environ.items() if k != "DUALSCALE_DEBUG"} | {"OMP_NUM_THREADS": "1",
                                                                       "PYTHONPATH": str(ROOT)}
FIT = ["--preset", "draft", "--threads", "1", "--cv-pixels", "0", "--checkpoint-every", "100000"]

# In the child: every image file under a folder, whole or not (reads its pixels back), and the rest.
CHECK = '''
def whole(p):
    import OpenImageIO as oiio
    if p.stat().st_size == 0:
        return False
    if p.suffix == ".png" and not p.read_bytes().endswith(b"IEND\\xaeB`\\x82"):
        return False
    inp = oiio.ImageInput.open(str(p))
    if inp is None:
        return False
    s = inp.spec()
    ok = inp.read_image(0, 0, 0, s.nchannels, "float") is not None
    inp.close()
    return ok

def listing(folder):
    return {str(p.relative_to(folder)): {"size": p.stat().st_size,
                                        "whole": whole(p) if p.suffix in (".exr", ".png") else None}
            for p in sorted(folder.rglob("*")) if p.is_file()}
'''


def _assert_nothing_short(files: dict) -> None:
    assert not any(".tmp-" in f for f in files), files
    assert all(v["size"] > 0 for v in files.values()), files
    assert all(v["whole"] is not False for v in files.values()), {f: v for f, v in files.items() if not v["whole"]}


# ---- a real full filesystem (tmpfs in a user namespace) ------------------------------------------

def _can_mount() -> bool:
    if shutil.which("unshare") is None:
        return False
    r = subprocess.run(["unshare", "-Urm", "sh", "-c", "d=$(mktemp -d) && mount -t tmpfs -o size=64k tmpfs $d"],
                       capture_output=True, timeout=30)
    return r.returncode == 0


needs_tmpfs = pytest.mark.skipif(not _can_mount(), reason="no unprivileged user+mount namespace (unshare -Urm) "
                                 "to mount a small tmpfs; the RLIMIT_FSIZE tests below cover the same writers")


FILL = '''
def fill(folder, leave_pages):
    """Fill the tmpfs so that exactly ``leave_pages`` pages stay free."""
    st = os.statvfs(MNT)
    page = st.f_frsize
    n = st.f_bavail - leave_pages
    with open(folder / "filler", "wb") as f:
        f.write(b"\\1" * (n * page))
    st = os.statvfs(MNT)
    assert st.f_bavail == leave_pages, (st.f_bavail, leave_pages)
    return page
'''


def _in_tmpfs(tmp_path: Path, body: str, size: str = "4m") -> dict:
    """Run ``body`` (Python, with ``MNT`` the mounted tmpfs, ``report`` the dict it fills, and
    ``fill``/``listing``) in
    a child in its own mount namespace, on a fresh tmpfs of ``size``; returns ``report``."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    script = tmp_path / "child.py"
    script.write_text(f"import json, os, subprocess, sys\nfrom pathlib import Path\nMNT = Path({str(mnt)!r})\n"
                      f"report = {{}}\n{CHECK}\n{FILL}\n{textwrap.dedent(body)}\nprint('REPORT ' + json.dumps(report))\n")
    r = subprocess.run(["unshare", "-Urm", "sh", "-c",
                        f"mount -t tmpfs -o size={size} tmpfs {mnt} && exec {sys.executable} {script}"],
                       capture_output=True, text=True, env=ENV, timeout=300, cwd=ROOT)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("REPORT ")]
    assert r.returncode == 0 and lines, r.stdout + r.stderr
    return json.loads(lines[-1][len("REPORT "):])


@needs_tmpfs
def test_a_full_disk_inside_a_preview_png_keeps_no_short_file_and_no_record(tmp_path):
    """``dualscale fit`` on a real filesystem that fills up half-way through ``albedo.png``
    (the first preview, which OpenImageIO would report written): exit 4 naming it, "disk full",
    no ``fit.json`` or ``material.json``, and every image left is whole."""
    from tests.units.conftest import small_dataset

    ds = small_dataset(tmp_path / "ds", size=64)
    report = _in_tmpfs(tmp_path, f'''
        def fit(out):
            return subprocess.run([sys.executable, "-m", "dualscale.cli", "fit", {str(ds)!r}, "-o", str(out),
                                   *{FIT!r}], capture_output=True, text=True)
        roomy = fit(MNT / "roomy")  # the same fit with room: its files' sizes, in the order written
        assert roomy.returncode == 0, roomy.stderr
        sizes = {{p.name: p.stat().st_size for p in (MNT / "roomy").iterdir()}}
        page = os.statvfs(MNT).f_frsize
        pages = lambda n: -(-n // page)
        assert pages(sizes["albedo.png"]) >= 2, sizes
        subprocess.run(["rm", "-r", str(MNT / "roomy")], check=True)
        # room for the folder's record, albedo.exr and half of albedo.png
        fill(MNT, pages(sizes[".dualscale-output.json"]) + pages(sizes["albedo.exr"]) + pages(sizes["albedo.png"]) // 2)
        r = fit(MNT / "out")
        report.update(rc=r.returncode, err=r.stderr, files=listing(MNT / "out"))
    ''')
    last = report["err"].splitlines()[-1]
    assert report["rc"] == 4, report["err"]
    assert last.startswith("dualscale fit: error: cannot write ") and "albedo.png" in last, report["err"]
    assert "disk full" in last and "No space left on device" in last, last
    assert "Traceback" not in report["err"]
    files = report["files"]
    assert "fit.json" not in files and "material.json" not in files and "albedo.png" not in files, files
    assert files["albedo.exr"]["whole"], files
    _assert_nothing_short(files)


@needs_tmpfs
@pytest.mark.parametrize("writer", ["exr", "png", "rows"])
def test_each_image_writer_on_a_full_disk(tmp_path, writer):
    """``write_exr``, ``write_png_preview`` and the row writer (``MapsWriter``, with previews)
    into a real filesystem with one free page: ``OutputError`` ENOSPC naming the file, nothing
    under a final name."""
    report = _in_tmpfs(tmp_path, f'''
        import numpy as np
        from dualscale.errors import OutputError
        from dualscale.formats.exr import write_exr, write_png_preview
        from dualscale.formats.maps import MapsWriter
        img = np.random.default_rng(0).random((128, 128, 3)).astype(np.float32)
        out = MNT / "out"
        out.mkdir()
        fill(MNT, 1)
        try:
            if {writer!r} == "exr":
                write_exr(out / "a.exr", img)
            elif {writer!r} == "png":
                write_png_preview(out / "a.png", img)
            else:
                with MapsWriter(out, ["albedo", "roughness"], 128, 128, previews=True) as w:
                    for y in range(0, 128, 32):
                        w.write(y, {{"albedo": img[y:y + 32], "roughness": img[y:y + 32, :, 0]}})
            report["error"] = None
        except OutputError as e:
            report["error"] = [e.errno, e.filename, str(e)]
        report["files"] = listing(out)
    ''')
    assert report["error"] is not None, report
    code, filename, text = report["error"]
    assert code == errno.ENOSPC and "disk full" in text and filename.startswith(str(tmp_path / "mnt" / "out")), text
    assert "material.json" not in report["files"]
    _assert_nothing_short(report["files"])


# ---- the kernel's file-size limit (RLIMIT_FSIZE) -------------------------------------------------

def _limited(limit: int):
    def pre() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return pre


WRITE = '''
import numpy as np
from dualscale.errors import OutputError
img = np.random.default_rng(0).random((64, 64, 3))
out = Path(sys.argv[1]) / "out"
out.mkdir(exist_ok=True)
try:
    if WRITER == "preview":
        from dualscale.formats.exr import write_png_preview
        write_png_preview(out / "a.png", img)
    elif WRITER == "texture":
        from dualscale.export.textures import write_png
        write_png(out / "a.png", img, srgb=False, bits=16)
    elif WRITER == "exr":
        from dualscale.formats.exr import write_exr
        write_exr(out / "a.exr", img)
    else:
        from dualscale.formats.atomic import write_bytes
        write_bytes(out / "a.bin", bytes(20000))
    report["error"] = None
except OutputError as e:
    report["error"] = [e.errno, e.filename, str(e)]
report["files"] = listing(out)
'''


@pytest.mark.parametrize("limit", [0, 700, 6000])
@pytest.mark.parametrize("writer", ["preview", "texture", "exr", "bytes"])
def test_a_write_cut_by_the_file_size_limit_keeps_no_final_name(tmp_path, writer, limit):
    """Every writer, cut at 0, 700 and 6000 bytes (inside the header, inside the pixels; every
    one of these files is larger): ``OutputError`` EFBIG naming the final file, no file left."""
    script = tmp_path / "child.py"
    script.write_text(f"import json, sys\nfrom pathlib import Path\nWRITER = {writer!r}\nreport = {{}}\n{CHECK}\n"
                      f"{WRITE}\nprint('REPORT ' + json.dumps(report))\n")
    r = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, env=ENV,
                       timeout=120, cwd=ROOT, preexec_fn=_limited(limit))
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("REPORT ")]
    assert r.returncode == 0 and lines, r.stdout + r.stderr
    report = json.loads(lines[-1][len("REPORT "):])
    assert report["error"] is not None, report
    code, filename, text = report["error"]
    assert code == errno.EFBIG and "File too large" in text and filename == str(tmp_path / "out" / f"a.{'exr' if writer == 'exr' else 'bin' if writer == 'bytes' else 'png'}"), text
    assert report["files"] == {}, report["files"]


# ---- the OS boundary: fsync fails --------------------------------------------------------------

@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EIO])
def test_fsync_failing_leaves_no_file(tmp_path, monkeypatch, code):
    """A filesystem that reports the lost bytes only at fsync (delayed allocation, NFS): the
    writer's OutputError names the final file, and neither it nor a temporary file is left; an
    earlier file under that name stays as it was."""
    target = tmp_path / "a.exr"
    write_exr(target, np.zeros((4, 4, 3)))
    before = target.read_bytes()
    real = os.fsync

    def fsync(fd):
        if not stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(code, os.strerror(code))
        return real(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    with pytest.raises(OutputError) as e:
        write_exr(target, np.ones((4, 4, 3)))
    assert e.value.errno == code and e.value.filename == str(target) and os.strerror(code) in str(e.value)
    with pytest.raises(OutputError):
        write_png_preview(tmp_path / "b.png", np.ones((4, 4, 3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr"] and target.read_bytes() == before


def test_a_folder_fsync_that_fails_removes_the_new_file(tmp_path, monkeypatch):
    """The rename is durable only once the folder is flushed: an I/O error there removes the new
    file rather than leave it under its final name; a filesystem that cannot flush folders
    (EINVAL) is let be."""
    real = os.fsync
    answer = {"code": errno.EIO}

    def fsync(fd):
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(answer["code"], os.strerror(answer["code"]))
        return real(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    with pytest.raises(OutputError) as e:
        atomic.write_json(tmp_path / "fit.json", {"a": 1})
    assert e.value.errno == errno.EIO and list(tmp_path.iterdir()) == []
    answer["code"] = errno.EINVAL
    atomic.write_json(tmp_path / "fit.json", {"a": 1})
    assert json.loads((tmp_path / "fit.json").read_text()) == {"a": 1}


def test_output_error_is_exit_4_in_the_error_tree():
    from dualscale.cli import exit_code
    from dualscale.errors import EXIT_CODES, DualscaleError, ToolError

    e = atomic.output_error("/x/a.exr", OSError(errno.ENOSPC, "No space left on device"))
    assert isinstance(e, OutputError) and isinstance(e, OSError) and isinstance(e, ToolError)
    assert isinstance(e, DualscaleError) and exit_code(e) == EXIT_CODES["tool"] == 4
    assert str(e).startswith("cannot write /x/a.exr: disk full (No space left on device)")
    assert atomic.output_error("/x/a.exr", OSError(errno.EACCES, "Permission denied")) is None
