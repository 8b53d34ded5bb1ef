"""Side-by-side comparison images: one shared exposure, one PNG per render, contact sheets.

Every image under one light is tone-mapped with the same exposure
(:func:`dermis.reports.tonemap.shared_exposure` over all models and geometries under that light),
so brightness differences between models are real differences, not tone-mapping
artefacts.  Lights differ by orders of magnitude (a sunset sky vs one point light), so
each light gets its own exposure; all exposures are saved in ``exposure.json``.
"""
from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from PIL import Image

from dermis.reports.sheets import caption, grid, ordered_models, save_png, thumbnail
from dermis.reports.tonemap import encode_srgb8, shared_exposure

__all__ = ["write_pngs", "contact_sheet", "contact_sheet_image", "load_thumbnails"]


def _label(image) -> tuple[str, str, str]:
    info = image.info
    return info.get("model", "?"), info.get("light", "?"), info.get("geometry", "?")


def write_pngs(images: dict, out_dir: Path, *, thumbnails: bool = False) -> list[Path]:
    """Write ``<model>-<light>-<geometry>.png`` per image and one contact sheet per geometry.

    Parameters
    ----------
    images : dict node id -> :class:`pipeline.artifacts.RenderedImage`
    out_dir : directory to write into
    thumbnails : also write ``thumb-<model>-<light>-<geometry>.png`` (the contact sheets'
        tiles, :data:`reports.sheets.TILE_PX`) for the report's image pages (not returned)

    Returns
    -------
    list of written paths (PNGs and ``exposure.json``)

    Each image is tone-mapped once (:func:`dermis.reports.tonemap.encode_srgb8`); the sheets
    paste thumbnails of those PNGs (:mod:`dermis.reports.sheets`), and the PNGs are encoded
    on two threads (zlib releases the GIL).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ids = sorted(images)
    exposures, mapped = {}, {}
    for light in sorted({_label(images[i])[1] for i in ids}):
        group = [i for i in ids if _label(images[i])[1] == light]
        exposures[light] = shared_exposure([images[i].linear for i in group])
        for i in group:
            mapped[i] = encode_srgb8(images[i].linear, exposures[light])
    jobs = [(out_dir / ("%s-%s-%s.png" % _label(images[nid])), mapped[nid]) for nid in ids]
    thumbs = [(out_dir / ("thumb-%s-%s-%s.png" % _label(images[nid])), thumbnail(mapped[nid]))
              for nid in ids] if thumbnails else []
    for geom in sorted({_label(images[i])[2] for i in ids}):
        sel = {i: mapped[i] for i in ids if _label(images[i])[2] == geom}
        jobs.append((out_dir / f"sheet-{geom}.png",
                     contact_sheet_image({i: images[i] for i in sel}, sel,
                                         title=f"geometry: {geom}")))
    with ThreadPoolExecutor(2) as pool:
        files = list(pool.map(lambda job: save_png(*job), jobs))
        list(pool.map(lambda job: save_png(*job), thumbs))
    (out_dir / "exposure.json").write_text(json.dumps({"exposure_per_light": exposures, "images": ids},
                                                     indent=1))
    files.append(out_dir / "exposure.json")
    return files


def contact_sheet_image(images: dict, mapped: dict, *, title: str = ""):
    """A labelled grid (uint8 RGB): rows are models (``bssrdf_mc`` labelled "BSSRDF (Monte
    Carlo profile)"), columns are lights, seconds per image
    under each label (the render node's own time; the shared visibility node is timed on
    its own)."""
    labels = {i: _label(images[i]) for i in images}
    models = ordered_models(m for m, _, _ in labels.values())
    lights = sorted({l for _, l, _ in labels.values()})
    tiles, caps = {}, {}
    for i, (m, l, _) in labels.items():
        tiles[(m, l)] = mapped[i]
        t = images[i].timings.get("total")
        caps[(m, l)] = caption(m, l) + (f"\n{t:.1f} s" if t else "")
    return grid(tiles, models, lights, captions=caps, title=title)


def contact_sheet(images: dict, mapped: dict, path: Path, *, title: str = "") -> Path:
    """:func:`contact_sheet_image` written to ``path`` (PNG)."""
    return save_png(path, contact_sheet_image(images, mapped, title=title))


def load_thumbnails(folder) -> tuple[dict, dict]:
    """(thumbnails {(model, light, geometry): uint8 image}, exposure per light) that an
    ``images`` node wrote (:func:`write_pngs` with ``thumbnails``)."""
    folder = Path(folder)
    out = {}
    for path in sorted(folder.glob("thumb-*.png")):
        model, rest = path.stem[len("thumb-"):].split("-", 1)
        light, geom = rest.rsplit("-", 1)
        with Image.open(path) as im:
            out[(model, light, geom)] = np.asarray(im.convert("RGB"))
    exposure = json.loads((folder / "exposure.json").read_text())["exposure_per_light"]
    return out, exposure
