"""Figures of ``dermis sweep``: error against time per knob (median seconds with their
min-max spread, error with its uncertainty, Pareto front, default starred), a joint one, and
the recommendations as predicted and as rendered; all pages also in ``sweep.pdf``."""
from __future__ import annotations

from pathlib import Path

__all__ = ["plots"]


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def _knob_page(plt, result: dict, name: str, front: list[int]):
    rows = result["points"]
    joint = name == "joint"
    sel = [k for k, r in enumerate(rows)
           if (name in ("joint", "grid") or r["knob"] == name) and r.get("rel_rmse") is not None]
    if not sel:
        return None
    tkey = "seconds_total" if joint else "seconds"
    off = (lambda r: r["seconds_shared"]) if joint else (lambda r: 0.0)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for k in sel:
        r = rows[k]
        x, y = r[tkey], r["rel_rmse"]
        xerr = [[x - (r["seconds_min"] + off(r))], [(r["seconds_max"] + off(r)) - x]]
        unc = r.get("error_uncertainty") or 0.0
        ax.errorbar(x, y, xerr=xerr, yerr=[[min(unc, y)], [unc]] if unc else None,
                    fmt="*" if r["is_default"] else "o", ms=11 if r["is_default"] else 5,
                    color="C3" if r["is_default"] else "C0", ecolor="0.5", elinewidth=0.8,
                    capsize=2, zorder=3)
        ax.annotate(",".join(map(_fmt, r["values"].values())), (x, y), fontsize=7,
                    xytext=(3, 3), textcoords="offset points")
    f = [k for k in front if k in sel]
    ax.plot([rows[k][tkey] for k in f], [rows[k]["rel_rmse"] for k in f], "-", color="C1",
            label="Pareto front (medians)")
    for t in result["targets"]:
        ax.axhline(t, color="0.6", lw=0.8, ls=":")
    what = "all the point's nodes" if joint else "the nodes the knob changes"
    ax.set_xlabel(f"seconds of {what}: median of {result['repeats']} runs, bars min-max")
    ax.set_ylabel("relative RMSE against the converged reference")
    if all(rows[k]["rel_rmse"] > 0 for k in sel):
        ax.set_yscale("log")
    ref = result["reference_rules"].get(name, "per knob")
    ex = result.get("extrapolation", {}).get(name)
    if ex and ex.get("finest_error") is not None:
        ref = f"finest + extrapolated error {ex['finest_error']:.2g} (order {ex['order']:.2g})"
    ax.set_title(f"{name}  (reference: {ref});  default = star", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def _recommended_page(plt, result: dict):
    recs = {g: r for g, r in result.get("recommended", {}).items()
            if r and (r.get("config") or r.get("misses"))}
    if not recs:
        return None
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for n, (goal, rec) in enumerate(recs.items()):
        tried = list(rec.get("misses", [])) + ([rec] if rec.get("config") else [])
        for e in tried:
            p, m = e.get("predicted"), e.get("measured")
            if not m or m.get("rel_rmse") is None:
                continue
            p = p or m
            ok = e is rec and bool(rec.get("meets"))
            label = (f"{goal}: " + ("recommended" if ok else "rendered, missed")
                     if goal != "defaults" else "scene as written (rendered)")
            ax.plot([p["seconds"], m["seconds"]], [p["rel_rmse"], m["rel_rmse"]], "-",
                    color=f"C{n}", lw=0.8)
            ax.scatter(p["seconds"], p["rel_rmse"], marker="o", facecolors="none",
                       edgecolors=f"C{n}", s=40, zorder=3)
            ax.scatter(m["seconds"], m["rel_rmse"],
                       marker="*" if goal == "defaults" else "s" if ok else "x",
                       color=f"C{n}", s=60 if goal == "defaults" else 40, zorder=3, label=label)
    for t in result["targets"]:
        ax.axhline(t, color="0.6", lw=0.8, ls=":")
    ax.set_xlabel("seconds of the configuration's nodes (median)")
    ax.set_ylabel("relative RMSE against the converged reference")
    ax.set_title("recommendations: predicted (open circle, first order) -> rendered\n"
                 "(square: meets its goal, x: rendered and missed it, star: scene as written)",
                 fontsize=9)
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    ax.legend(uniq.values(), uniq.keys(), fontsize=7)
    fig.tight_layout()
    return fig


def plots(result: dict, out: Path) -> None:
    """Write sweep-<knob>.png, sweep-joint.png, sweep-recommended.png and sweep.pdf."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    with PdfPages(out / "sweep.pdf") as pdf:
        pages = [(name, _knob_page(plt, result, name, front))
                 for name, front in result["fronts"].items()]
        pages.append(("recommended", _recommended_page(plt, result)))
        for name, fig in pages:
            if fig is None:
                continue
            fig.savefig(out / f"sweep-{name.replace('.', '_')}.png", dpi=110)
            pdf.savefig(fig)
            plt.close(fig)
