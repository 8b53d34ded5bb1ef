"""The report's "What this scene requires" pages: one per view, rows lighting condition x
face region, columns each effect's size with its verdict and the cheapest model that meets
the accuracy (:mod:`dermis.reports.requirements`)."""
from __future__ import annotations

from dermis.models import catalog
from dermis.reports.requirements import EFFECTS

__all__ = ["requirement_pages", "requirement_lines"]

_MARK = {"visible": "visible", "absent": "absent", "unresolved": "?"}


def _effect_cell(e: dict | None) -> str:
    if not e:
        return ""
    if not e.get("measured"):
        return "n.m."
    return f"{100 * e['signed']:+.1f} {_MARK[e['verdict']]}"


def _model_cell(row: dict) -> str:
    m = row.get("cheapest")
    if m is None:
        return "none" if row.get("models") else "–"
    v = row["models"][m]
    return f"{catalog.label(m)} ({100 * v['error']:+.1f} %, {v['seconds']:.1f} s)"


def requirement_lines(requires: dict, view: str) -> list[tuple[str, str]]:
    """(lighting condition, sentence) per condition of ``view``: the visible effects and the
    cheapest model that meets the accuracy everywhere."""
    out = []
    for light, rec in sorted(requires.get(view, {}).items()):
        visible = sorted({name for row in rec["regions"].values()
                          for name, e in row["effects"].items()
                          if e.get("measured") and e["verdict"] == "visible"})
        best = rec.get("cheapest_everywhere")
        out.append((light, ("visible: " + ", ".join(visible) if visible else
                            "no measured effect visible")
                    + "; cheapest adequate everywhere: "
                    + (catalog.label(best) if best else "none")))
    return out


def requirement_pages(pdf, views: dict, *, accuracy: float, threshold: float,
                      figsize=(11.69, 8.27), max_rows: int = 34) -> int:
    """One page (or more) per view of metrics.json's ``views`` (``requires``, and ``auto``
    where ``["auto"]`` chose the models); returns the number of pages."""
    requires = {v: r["requires"] for v, r in views.items() if "requires" in r}
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from dermis.reports.pdf_report import MIN_FONT_PT, page_table

    names = [e.name for e in EFFECTS]
    header = ["light / region"] + names + ["cheapest adequate (error, time)", "against"]
    pages = 0
    for view in sorted(requires, key=lambda v: (v != "main", v)):
        cells = []
        for light, rec in sorted(requires[view].items()):
            for region, row in rec["regions"].items():
                cells.append([f"{light} / {region}"]
                             + [_effect_cell(row["effects"].get(n)) for n in names]
                             + [_model_cell(row), row.get("against") or "–"])
        for start in range(0, max(len(cells), 1), max_rows):
            chunk = cells[start:start + max_rows]
            fig = plt.figure(figsize=figsize)
            fig.suptitle(f"What this scene requires: view {view}", fontsize=12, y=0.975)
            ax = fig.add_axes([0.02, 0.16, 0.96, 0.77])
            ax.axis("off")
            if chunk:
                widths = [0.16] + [0.1] * (len(header) - 3) + [0.3, 0.14]
                page_table(ax, chunk, header, widths=[w / sum(widths) for w in widths],
                           row_height=0.028, fontsize=MIN_FONT_PT)
            lines = [f"{light}: {text}" for light, text in requirement_lines(requires, view)]
            lines += [f"{light}: [\"auto\"] rendered {catalog.label(a['model'])}; the "
                      f"{100 * a['accuracy']:.0f} % target {a['target']}"
                      for light, a in sorted(views[view].get("auto", {}).items())]
            meaning = "; ".join(f"{e.name} = {e.meaning}" for e in EFFECTS)
            fig.text(0.02, 0.03, "\n".join(lines) + "\n\nEffect = image with / image without "
                     f"- 1 over the region's pixels, % of its mean: visible = above "
                     f"{100 * threshold:.0f} % by more than 2 s.e., absent = below it by as "
                     "much, ? = unresolved, n.m. not measured (its pair of images was not "
                     f"rendered). {meaning}. Cheapest adequate: the fastest model whose error "
                     f"against the truth is within {100 * accuracy:.0f} % by 2 s.e.",
                     fontsize=MIN_FONT_PT, va="bottom", wrap=True)
            pdf.savefig(fig)
            plt.close(fig)
            pages += 1
    return pages
