"""The report's profile page: the scene's layer-profile models against the Monte Carlo table.

One page (the models and the measurements behind them: docs/profiles.md):

* top row, per colour channel: r R(r) on log axes (the energy per unit log-radius, so the
  near-source peak and the far tail are both readable) for every profile model the scene
  computes (the multipole the ``bssrdf`` images use, the Monte Carlo table of the
  ``bssrdf_mc`` images), the Monte Carlo table with its per-ring noise band;
* middle row: each model's ring energy on the Monte Carlo rings relative to the table's,
  with the table's own +-2 standard-error band (what the comparison cannot resolve);
* bottom: Rd and Tt of every model per channel, their error against the Monte Carlo (with
  its standard error) and the R(r) error over [0.05, 5] mm
  (:func:`dermis.optics.profile_command.profile_errors`: misplaced energy, largest error).

Rd and Tt are per photon that entered the top surface (the specular reflection at entry
not counted; ``optics.layer_file.RD_CONVENTION``).  Without a Monte Carlo table in the scene
the page shows the scene's profile alone and says how to add the table.
"""
from __future__ import annotations

import numpy as np

from dermis.optics.profile_command import ERROR_BAND_MM, profile_errors, ring_energy

__all__ = ["profile_pages", "PAGES", "BAND_MM", "NOISE_BAND_SIGMA"]

PAGES = 1
BAND_MM = (0.02, 10.0)          # radii drawn (mm); the error columns use profile_command's band
NOISE_BAND_SIGMA = 2.0          # the Monte Carlo band: +-2 standard errors per ring
Y_DECADES = 1e-5                # r R(r) drawn over five decades below its peak (a drawing choice)
# Minor grid lines of the log axes at 2 and 5 x each decade (a 1-2-5 grid) instead of
# matplotlib's 2..9: the page drew ~300 minor ticks, 0.2 s of its CPU time (py-spy).
MINOR_SUBS = (2.0, 5.0)
CHANNELS = ("red", "green", "blue")
_STYLE = {"multipole": dict(color="C0", lw=1.4), "diffusion": dict(color="C2", lw=1.2, ls="--"),
          "dj2005": dict(color="C3", lw=1.0, ls=":")}


def _label(prof) -> str:
    m = prof.info.get("model", "multipole")
    if m == "monte_carlo":
        return (f"Monte Carlo table ({prof.info.get('photons', 0):,} photons/channel, "
                f"seed {prof.info.get('seed', '?')})")
    return {"multipole": "multipole (diffusion shapes, exact totals)"}.get(m, m)


def _mc_rings(mc):
    """(edges, mid radii, ring energies (B, 3), their standard errors (B, 3)) of a table."""
    edges = np.asarray(mc.info["r_edges"], np.float64)
    area = np.pi * np.diff(edges**2)[:, None]
    mid = 0.5 * (edges[1:] + edges[:-1])
    return edges, mid, mc.R * area, np.asarray(mc.info["R_err"]) * area


def profile_pages(pdf, profiles: dict) -> int:
    """Add the profile page to the open ``PdfPages`` ``pdf``; returns the pages added.

    ``profiles``: node id -> :class:`pipeline.artifacts.LayerProfile` (the scene's profiles
    nodes; at most one Monte Carlo table is the reference, the first by node id).
    """
    import matplotlib.pyplot as plt

    if not profiles:
        return 0
    # the PDF's core fonts have no Unicode minus sign
    with plt.rc_context({"axes.unicode_minus": False}):
        return _page(pdf, plt, profiles)


def _page(pdf, plt, profiles: dict) -> int:
    from matplotlib.ticker import LogLocator
    profs = [profiles[k] for k in sorted(profiles)]
    mcs = [p for p in profs if p.info.get("model") == "monte_carlo"]
    mc = mcs[0] if mcs else None
    models = [p for p in profs if p is not mc]
    fig = plt.figure(figsize=(11.69, 8.27))
    fig.suptitle("Layer profiles: the scene's profile models against the Monte Carlo table",
                 fontsize=12, y=0.985)
    top = [fig.add_axes([0.06 + k * 0.32, 0.60, 0.26, 0.33]) for k in range(3)]
    mid = [fig.add_axes([0.06 + k * 0.32, 0.37, 0.26, 0.17]) for k in range(3)]
    errs = {id(p): profile_errors(p, mc) for p in models} if mc is not None else {}
    for c, (ax, ax2) in enumerate(zip(top, mid)):
        for p in models:
            r, y = p.r_mm, p.r_mm * p.R[:, c]
            sel = (r >= BAND_MM[0]) & (r <= BAND_MM[1]) & (y > 0)
            ax.plot(r[sel], y[sel], label=_label(p),
                    **_STYLE.get(p.info.get("model", "multipole"), dict(lw=1.2)))
        if mc is not None:
            edges, rm, e, se = _mc_rings(mc)
            sel = (rm >= BAND_MM[0]) & (rm <= BAND_MM[1]) & (mc.R[:, c] > 0)
            y = rm * mc.R[:, c]
            band = NOISE_BAND_SIGMA * rm * np.asarray(mc.info["R_err"])[:, c]
            ax.fill_between(rm[sel], np.maximum(y - band, y * 1e-3)[sel], (y + band)[sel],
                            color="0.6", alpha=0.5, lw=0,
                            label=f"Monte Carlo +-{NOISE_BAND_SIGMA:g} s.e.")
            ax.plot(rm[sel], y[sel], "k.", ms=2.5, label=_label(mc))
            noise = np.where(e[:, c] > 0, se[:, c] / np.where(e[:, c] > 0, e[:, c], 1), np.nan)
            ax2.fill_between(rm[sel], -NOISE_BAND_SIGMA * noise[sel],
                             NOISE_BAND_SIGMA * noise[sel], color="0.6", alpha=0.5, lw=0)
            for p in models:
                ep = ring_energy(p, edges)[:, c]
                ok = sel & (e[:, c] > 0)
                ax2.plot(rm[ok], ep[ok] / e[ok, c] - 1.0,
                         **_STYLE.get(p.info.get("model", "multipole"), dict(lw=1.2)))
            ax2.axhline(0.0, color="k", lw=0.6)
            ax2.axvspan(*ERROR_BAND_MM, color="C1", alpha=0.06, lw=0)
        else:
            ax2.text(0.5, 0.5, "no Monte Carlo table", ha="center", va="center",
                     transform=ax2.transAxes, fontsize=8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_minor_locator(LogLocator(subs=MINOR_SUBS))
        peak = max([float(np.max(p.r_mm * p.R[:, c])) for p in profs] + [1e-30])
        ax.set_ylim(peak * Y_DECADES, peak * 2.0)
        ax.set_title(f"{CHANNELS[c]}: r R(r)", fontsize=9)
        ax.set_xlim(*BAND_MM)
        ax.grid(True, which="both", alpha=0.25)
        ax.tick_params(labelsize=7)
        ax2.set_xscale("log")
        ax2.xaxis.set_minor_locator(LogLocator(subs=MINOR_SUBS))
        ax2.set_xlim(*BAND_MM)
        lim = 0.5
        if mc is not None and models:
            vals = [abs(v) for p in models for v in
                    (ring_energy(p, edges)[:, c][sel & (e[:, c] > 0)]
                     / e[sel & (e[:, c] > 0), c] - 1.0)]
            lim = float(np.clip(1.15 * max(vals + [0.02]), 0.02, 1.0))
        ax2.set_ylim(-lim, lim)
        ax2.set_xlabel("r (mm)", fontsize=8)
        ax2.grid(True, which="both", alpha=0.25)
        ax2.tick_params(labelsize=7)
        if c == 0:
            ax.set_ylabel("r R(r)  (1/mm)", fontsize=8)
            ax2.set_ylabel("ring energy / MC - 1", fontsize=8)
    top[0].legend(fontsize=6.5, loc="lower left")
    _table(fig, models, mc, errs)
    pdf.savefig(fig)
    plt.close(fig)
    return PAGES


def _pct(x, se=None) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{100 * x:+.1f} %" + (f" (+-{100 * se:.1f})" if se is not None else "")


def _table(fig, models, mc, errs) -> None:
    """Rd, Tt and the errors against the table, one row per model and channel."""
    header = ["model / channel", "Rd", "Tt", "Rd vs MC", "Tt vs MC",
              f"R(r) misplaced {ERROR_BAND_MM[0]:g}-{ERROR_BAND_MM[1]:g} mm",
              "largest R(r) error (at r)"]
    rows = []
    for p in models:
        for c in range(3):
            e = errs[id(p)]["channels"][c] if id(p) in errs else {}
            rows.append([f"{p.info.get('model', 'multipole')} / {CHANNELS[c]}",
                         f"{p.Rd[c]:.4f}", f"{p.Tt[c]:.4f}",
                         _pct(e.get("dRd"), e.get("Rd_se")), _pct(e.get("dTt"), e.get("Tt_se")),
                         _pct(e.get("R_misplaced")).lstrip("+"),
                         (_pct(e.get("R_max")) + f" ({e['R_max_at_mm']:.2f} mm)")
                         if e.get("R_max") is not None else "-"])
    if mc is not None:
        for c in range(3):
            rd_se, tt_se = mc.info["Rd_err"][c], mc.info["Tt_err"][c]
            rows.append([f"monte_carlo / {CHANNELS[c]}", f"{mc.Rd[c]:.4f} +-{rd_se:.4f}",
                         f"{mc.Tt[c]:.4f} +-{tt_se:.4f}", "reference", "reference",
                         f"ring noise <= {100 * mc.info.get('noise_max_rel', [np.nan] * 3)[c]:.2f} %",
                         "-"])
    ax = fig.add_axes([0.04, 0.06, 0.92, 0.25])
    ax.axis("off")
    if rows:
        tab = ax.table(cellText=rows, colLabels=header, cellLoc="center", loc="upper center",
                       colWidths=[0.16, 0.13, 0.13, 0.13, 0.13, 0.16, 0.16])
        tab.auto_set_font_size(False)
        tab.set_fontsize(7)
        tab.scale(1.0, 0.95)
        for (r, _), cell in tab.get_celld().items():
            if r == 0:
                cell.set_text_props(weight="bold")
    if mc is not None:
        note = ("Rd, Tt per photon that entered the top surface (specular reflection at entry "
                "not counted). Errors: model / Monte Carlo - 1, the table's standard error in "
                "brackets; R(r) on 24 log rings (dermis profile --mc; here on the model's own "
                "rings, the table's energy interpolated in r^2 within its rings). Grey bands: "
                f"the table's +-{NOISE_BAND_SIGMA:g} standard errors per ring. Monte Carlo "
                f"table: {mc.info.get('seconds', 0.0):.1f} s. The bssrdf_mc images use it; the "
                "bssrdf images the multipole (docs/profiles.md).")
    else:
        note = ("This scene computes no Monte Carlo table: add \"bssrdf_mc\" to [render] models "
                "(the BSSRDF with the Monte Carlo profile, beside the multipole one) or set "
                "[optics] profile = \"monte_carlo\" to see the diffusion model against it.")
    import textwrap
    fig.text(0.04, 0.30 - 0.0175 * (len(rows) + 2), textwrap.fill(note, 170), fontsize=7,
             color="0.25", va="top")
