"""HTML pages from Jinja2 templates shipped with the package, written atomically.

* Templates live in ``dualscale/report/templates/`` (package data); every page extends
  ``base.html``, which inlines ``report.css``: a report is one HTML file plus its images, with
  no script, no font and no URL outside its own folder, so it opens offline.
* Autoescaping is on for every template: values from run records are never trusted as HTML.
* :func:`write_atomic` writes a temporary file in the target's folder and ``os.replace``s it, so
  a reader never sees a half-written page.
"""

from __future__ import annotations

import shutil
from functools import lru_cache
from pathlib import Path
from typing import Any

from dualscale.formats.atomic import atomic_path, write_bytes

from . import format as fmt


@lru_cache(maxsize=1)
def environment():
    """The shared Jinja2 environment (autoescape on, undefined variables are errors)."""
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("dualscale.report", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters.update({
        "num": fmt.number, "qty": fmt.quantity, "pct": fmt.percent, "mm": fmt.length_mm,
        "size_mm": fmt.size_mm, "dur": fmt.duration, "val": fmt.value, "label": fmt.label,
        "hash": fmt.short_hash,
    })
    return env


def render(template: str, **context: Any) -> str:
    """Render a packaged template with ``context``."""
    return environment().get_template(template).render(**context)


def write_atomic(path: str | Path, data: str | bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:mod:`dualscale.formats.atomic`)."""
    return write_bytes(path, data.encode("utf-8") if isinstance(data, str) else data)


def write_page(path: str | Path, template: str, **context: Any) -> Path:
    """Render ``template`` and write it atomically to ``path``."""
    return write_atomic(path, render(template, **context))


class Assets:
    """The images of one report, kept in ``folder`` (``report/assets`` for a run report).

    :meth:`figure` saves a matplotlib figure as PNG (and SVG when asked), :meth:`copy` copies a
    file; both return the path relative to ``page_dir`` for ``<img src>``. Names are unique.
    """

    def __init__(self, page_dir: str | Path, folder: str | Path | None = "assets", svg: bool = False, dpi: int = 110):
        self.page_dir = Path(page_dir)
        self.dir = self.page_dir / folder if folder else self.page_dir
        self.dir.mkdir(parents=True, exist_ok=True)
        self.svg = svg
        self.dpi = dpi
        self._used: set[str] = set()

    def _name(self, stem: str) -> str:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in stem) or "figure"
        name, i = safe, 1
        while name in self._used:
            i += 1
            name = f"{safe}_{i}"
        self._used.add(name)
        return name

    def rel(self, path: Path) -> str:
        return path.relative_to(self.page_dir).as_posix()

    def figure(self, fig, stem: str) -> str:
        import matplotlib.pyplot as plt

        from .plots import settle

        name = self._name(stem)
        try:
            settle(fig)
            png = self.dir / f"{name}.png"
            fig.savefig(png, dpi=self.dpi)
            if self.svg:
                fig.savefig(self.dir / f"{name}.svg")
        finally:
            plt.close(fig)
        return self.rel(png)

    def copy(self, src: str | Path, stem: str | None = None) -> str:
        src = Path(src)
        name = self._name(stem or src.stem)
        dst = self.dir / f"{name}{src.suffix}"
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
        return self.rel(dst)


__all__ = ["environment", "render", "write_atomic", "write_page", "Assets"]
