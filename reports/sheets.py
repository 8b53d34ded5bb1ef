"""Labelled image grids drawn directly into pixels (numpy + Pillow), for contact sheets,
difference grids and the report's image pages.

Why not matplotlib: a 4 x 4 grid of subplots costs ~1 s to lay out and draw (axes, ticks,
tight bounding boxes), and the report drew a dozen of them; pasting thumbnails and drawing
two lines of text per tile costs milliseconds.  Fonts: matplotlib's bundled DejaVu Sans
(already a dependency), Pillow's default font if it is missing.  Deterministic: the same
tiles give the same pixels.
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

__all__ = ["font", "thumbnail", "grid", "colorbar", "hstack", "save_png", "TILE_PX",
           "PNG_COMPRESS_LEVEL", "caption", "ordered_models"]

# zlib level of the PNGs written here: 1 was ~3x faster than the default 6 on the 800 x 800
# renders (45 vs 130 ms) for files ~4 % larger.
PNG_COMPRESS_LEVEL = 1

# Thumbnail size of one tile (pixels, longer side): the old matplotlib sheets showed ~245 px
# tiles; 256 keeps them as sharp.
TILE_PX = 256
_PAD = 8


def caption(model: str, light: str, *, px: int = 11, width: int = TILE_PX) -> str:
    """A tile's caption: the model's display name (``models.catalog.label``: "BSSRDF (Monte
    Carlo profile)" for ``bssrdf_mc``) and the lighting condition, on one line if it fits
    ``width`` pixels at ``px`` (the grid's caption size), else the light on a line of its own."""
    from dermis.models.catalog import label as model_label
    text = f"{model_label(model)} / {light}"
    return text if font(px).getlength(text) <= width else f"{model_label(model)}\n{light}"


def ordered_models(models) -> list[str]:
    """The scene vocabulary's order (``dermis.MODELS``: the thesis's four, then bssrdf_mc),
    then anything else by name."""
    from dermis.models.catalog import ordered
    models = set(models)
    return ordered(models)


@functools.lru_cache(maxsize=16)
def font(size: int = 12, bold: bool = False):
    """DejaVu Sans (matplotlib's bundled font) at ``size`` px, else Pillow's default."""
    from PIL import ImageFont
    try:
        import matplotlib
        name = "DejaVuSans-Bold.ttf" if bold else "DejaVuSans.ttf"
        return ImageFont.truetype(str(Path(matplotlib.get_data_path()) / "fonts" / "ttf" / name),
                                  size)
    except Exception:  # pragma: no cover - no matplotlib fonts: still readable
        return ImageFont.load_default()


def thumbnail(image: np.ndarray, px: int = TILE_PX) -> np.ndarray:
    """(h, w, 3) uint8 reduced so the longer side is ``px`` (box filter = area average);
    images already that small are returned as they are."""
    from PIL import Image
    image = np.asarray(image)
    h, w = image.shape[:2]
    scale = px / max(h, w)
    if scale >= 1:
        return image
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return np.asarray(Image.fromarray(image).resize(size, Image.BOX))


def _text_height(f) -> int:
    box = f.getbbox("Ag")
    return int(box[3] - min(box[1], 0)) + 2


def grid(tiles: dict, rows: list, cols: list, *, captions: dict | None = None, title: str = "",
         tile_px: int = TILE_PX, caption_px: int = 11, title_px: int = 14,
         footer: np.ndarray | None = None, background: int = 255) -> np.ndarray:
    """A labelled grid: ``tiles[(row, col)]`` (uint8 RGB) at ``rows`` x ``cols`` positions,
    each under its caption (``captions[(row, col)]``, lines split on newlines), a title on
    top and an optional ``footer`` image (e.g. colour bars) below.  Empty cells stay blank.

    Returns (H, W, 3) uint8.
    """
    from PIL import Image, ImageDraw

    captions = captions or {}
    fc, ft = font(caption_px), font(title_px)
    lines = max([len(str(c).split("\n")) for c in captions.values()] + [1])
    cap_h = lines * _text_height(fc) + 2
    title_h = _text_height(ft) + 2 * _PAD if title else _PAD
    cell_w, cell_h = tile_px + _PAD, tile_px + cap_h + _PAD
    width = _PAD + len(cols) * cell_w
    foot_h = 0 if footer is None else footer.shape[0] + _PAD
    height = title_h + len(rows) * cell_h + foot_h + _PAD
    width = max(width, 0 if footer is None else footer.shape[1] + 2 * _PAD)
    canvas = Image.new("RGB", (width, height), (background,) * 3)
    draw = ImageDraw.Draw(canvas)
    if title:
        tw = draw.textlength(title, font=ft)
        draw.text(((width - tw) / 2, _PAD), title, fill=(0, 0, 0), font=ft)
    for (r, c), tile in tiles.items():
        if r not in rows or c not in cols:
            continue
        x0 = _PAD + cols.index(c) * cell_w
        y0 = title_h + rows.index(r) * cell_h
        th = thumbnail(tile, tile_px)
        ox = x0 + (tile_px - th.shape[1]) // 2
        oy = y0 + cap_h + (tile_px - th.shape[0]) // 2
        canvas.paste(Image.fromarray(np.ascontiguousarray(th)), (ox, oy))
        for k, line in enumerate(str(captions.get((r, c), "")).split("\n")):
            lw = draw.textlength(line, font=fc)
            draw.text((x0 + (tile_px - lw) / 2, y0 + k * _text_height(fc)), line,
                      fill=(0, 0, 0), font=fc)
    if footer is not None:
        canvas.paste(Image.fromarray(np.ascontiguousarray(footer)),
                     ((width - footer.shape[1]) // 2, height - foot_h))
    return np.asarray(canvas)


def colorbar(lut: np.ndarray, vmin: float, vmax: float, label: str, *, width: int = 240,
             height: int = 12, ticks: int = 5, text_px: int = 10) -> np.ndarray:
    """A horizontal colour bar of ``lut`` ((n, 3) floats in [0, 1]) from vmin to vmax with
    ``ticks`` labelled ticks and a label underneath: (h, width, 3) uint8."""
    from PIL import Image, ImageDraw

    f = font(text_px)
    th = _text_height(f)
    img = Image.new("RGB", (width + 2 * _PAD * 3, height + 2 * th + 8), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    x0 = _PAD * 3
    idx = np.minimum((np.arange(width) * len(lut)) // width, len(lut) - 1)
    bar = np.round(np.asarray(lut)[idx] * 255).astype(np.uint8)
    img.paste(Image.fromarray(np.ascontiguousarray(np.repeat(bar[None], height, axis=0))),
              (x0, 0))
    for k in range(ticks):
        t = k / (ticks - 1)
        x = x0 + t * (width - 1)
        draw.line([(x, height), (x, height + 3)], fill=(0, 0, 0))
        s = f"{vmin + t * (vmax - vmin):.3g}"
        draw.text((x - draw.textlength(s, font=f) / 2, height + 3), s, fill=(0, 0, 0), font=f)
    draw.text((x0 + (width - draw.textlength(label, font=f)) / 2, height + 3 + th), label,
              fill=(0, 0, 0), font=f)
    return np.asarray(img)


def hstack(images: list, *, gap: int = _PAD, background: int = 255) -> np.ndarray:
    """Images side by side (top-aligned) on a white background."""
    h = max(im.shape[0] for im in images)
    w = sum(im.shape[1] for im in images) + gap * (len(images) - 1)
    out = np.full((h, w, 3), background, np.uint8)
    x = 0
    for im in images:
        out[:im.shape[0], x:x + im.shape[1]] = im
        x += im.shape[1] + gap
    return out


def save_png(path, image: np.ndarray, *, palette: np.ndarray | None = None) -> Path:
    """Write an 8-bit PNG with Pillow (no time stamp: the same pixels give the same bytes).

    image : (H, W, 3) uint8 RGB, or (H, W) uint8 palette indices with ``palette`` an (n, 3)
    uint8 table (n <= 256): a palette PNG, a third of the data to compress.
    """
    from PIL import Image
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    im = Image.fromarray(np.ascontiguousarray(image))
    if palette is not None:
        im = Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8), mode="P")
        im.putpalette(np.asarray(palette, dtype=np.uint8).ravel().tolist())
    im.save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return path
