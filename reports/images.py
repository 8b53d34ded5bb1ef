"""Side-by-side comparison images: one shared exposure, one PNG per render, contact sheets.

Every image under one light is tone-mapped with the same exposure
(:func:`dermis.reports.tonemap.shared_exposure` over all models and geometries under that light),
so brightness differences between models are real differences, not tone-mapping
artefacts.  Lights differ by orders of magnitude (a sunset sky vs one point light), so
each light gets its own exposure; all exposures are saved in ``exposure.json``.
"""
from __future__ import annotations

import json
from pathlib import Path

from dermis.pipeline.graph import Node, StageResult

__all__ = ["write_pngs", "contact_sheet", "NAME", "node", "run"]

NAME = "images"
VERSION = 1
KERNELS = ()


def _label(image) -> tuple[str, str, str]:
    info = image.info
    return info.get("model", "?"), info.get("light", "?"), info.get("geometry", "?")


def write_pngs(images: dict, out_dir: Path) -> list[Path]:
    """Write ``<model>-<light>-<geometry>.png`` per image and one contact sheet per geometry.

    Parameters
    ----------
    images : dict node id -> :class:`pipeline.artifacts.RenderedImage`
    out_dir : directory to write into

    Returns
    -------
    list of written paths (PNGs and ``exposure.json``)
    """
    from dermis.pipeline.imageio import write_png
    from dermis.reports.tonemap import shared_exposure, tonemap

    out_dir = Path(out_dir)
    ids = sorted(images)
    exposures, mapped = {}, {}
    for light in sorted({_label(images[i])[1] for i in ids}):
        group = [i for i in ids if _label(images[i])[1] == light]
        exposures[light] = shared_exposure([images[i].linear for i in group])
        mapped.update(zip(group, tonemap([images[i].linear for i in group],
                                         exposure=exposures[light])))
    files = []
    for nid in ids:
        model, light, geom = _label(images[nid])
        files.append(write_png(out_dir / f"{model}-{light}-{geom}.png", mapped[nid]))
    for geom in sorted({_label(images[i])[2] for i in ids}):
        sel = {i: mapped[i] for i in ids if _label(images[i])[2] == geom}
        files.append(contact_sheet({i: images[i] for i in sel}, sel,
                                   out_dir / f"sheet-{geom}.png", title=f"geometry: {geom}"))
    (out_dir / "exposure.json").write_text(json.dumps({"exposure_per_light": exposures, "images": ids},
                                                     indent=1))
    files.append(out_dir / "exposure.json")
    return files


def contact_sheet(images: dict, mapped: dict, path: Path, *, title: str = "") -> Path:
    """A labelled grid: rows are models, columns are lights (matplotlib)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {i: _label(images[i]) for i in images}
    models = sorted({m for m, _, _ in labels.values()})
    lights = sorted({l for _, l, _ in labels.values()})
    fig, axes = plt.subplots(len(models), len(lights), squeeze=False,
                             figsize=(2.6 * len(lights), 2.6 * len(models) + 0.4))
    for ax in axes.flat:
        ax.axis("off")
    for i, (m, l, _) in labels.items():
        ax = axes[models.index(m), lights.index(l)]
        ax.imshow(mapped[i])
        t = images[i].timings.get("total")
        ax.set_title(f"{m} / {l}" + (f"\n{t:.1f} s" if t else ""), fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


# --------------------------------------------------------------------------- stage
def node(scene, render_ids: list[str]) -> Node:
    """Tone-map every rendered image (one exposure per lighting condition), PNGs + sheets."""
    return Node(NAME, NAME, __name__, {"renders": sorted(render_ids)}, tuple(render_ids),
                label="tone-mapped PNGs")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    files = write_pngs({nid: inputs[nid] for nid in params["renders"]}, ctx.out_dir)
    return StageResult(files=[f.name for f in files])
