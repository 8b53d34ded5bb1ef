"""``dermis profile LAYERS.toml [--csv OUT.csv] [--mc PHOTONS]``: layer files and their error.

Without ``--mc`` it prints one line per channel, ``channel Rd Tt``, for the multipole model
(the interface other tools read), and with ``--csv`` writes ``r_mm,R_r,R_g,R_b,T_r,T_g,T_b``
(1/mm^2, ring averages on the layer-file rings, integral 2 pi r R dr = Rd).

With ``--mc PHOTONS`` it also runs the OpenCL Monte Carlo on the same rings (the reference),
adds its columns ``MC_R_*``, ``MC_T_*`` and standard errors ``MC_R_*_err``, ``MC_T_*_err``
to the CSV, and prints per profile model and channel Rd, Tt and their error against the
reference (with the reference's own standard error) and the R(r) error over [0.05, 5] mm
(misplaced energy, rms and largest relative error on 24 log-spaced rings).  The models:

* ``multipole``: the BSSRDF's default (diffusion shapes, exact plane-parallel totals);
* ``diffusion``: the same diffusion with its own totals (the diffusion model's own error);
* ``dj2005``: the multipole of dermis <= 1 (Donner-Jensen 2005 as implemented before);
* ``monte_carlo``: a Monte Carlo table as the BSSRDF would use it, from another seed.

Convention (CSV header and output): R and T per photon that entered the top surface; the
specular reflection at entry is not counted (per incident photon: times 1 - R_sp).

Before any work the options are checked against the bounds the scene schema uses
(``--mc`` as ``[optics] photons``, ``--seed`` as ``[optics] seed``; ``--poles`` up to the
adaptive count's cap) and the peak memory is estimated (:func:`estimate_memory`) against the
machine's, as for scenes: a problem exits with code 2 and a message naming the option.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from dermis.pipeline import cl as dcl
from dermis.pipeline.resources import MEMORY_ENV_VAR, machine_memory
from dermis.pipeline.errors import DermisError
from dermis.optics.fresnel import fresnel_normal
from dermis.optics.layer_file import auto_grid
from dermis.optics.layers import MAX_MC_PHOTONS, PRESETS, LayerStack, load_layers_toml
from dermis.optics.multipole import (IMAGE_SUM_CHUNK, MAX_POLES, beam_sources,
                                     diffusion_constants, relative_indices)

__all__ = ["add_parser", "run", "check_options", "estimate_memory", "MODELS", "ERROR_BAND_MM"]

MODELS = ("multipole", "diffusion", "dj2005", "monte_carlo")
ERROR_BAND_MM = (0.05, 5.0)
ERROR_RINGS = 24
# Largest --seed: the monte_carlo model runs seed + 1, and seeds are 0 .. 2**32 - 1 (the
# scene's [optics] seed).
MAX_SEED = 2**32 - 2

# Peak memory of ``dermis profile`` (resident set size, 2-core PoCL machine; estimate_memory's
# sum against it): the interpreter with numpy and scipy, 60 MiB (skin1; 68 MiB estimated); a
# layered stack's FFT adding holds about 26 + 5 x (layers - 2) grids of (2n + 1)^2 float64
# (the collimated light a layer passes on is a grid where it spreads), at most FFT_GRIDS_MAX; the image sums IMAGE_SUM_ARRAYS float64 arrays of (radii x images)
# pairs, in chunks of IMAGE_SUM_CHUNK unless one radius has more; the OpenCL Monte Carlo its
# runtime, buffers and diffusion guide.  Measured (estimated), MiB: two_layer (n = 800) 533
# (719), with --poles 2000 697 (755); with --mc 20000 644, 3 layers at n = 1024 1009 and 5
# layers 1034 were measured while the collimated light was a number (24 + 4 x (layers - 2)
# grids: estimated 808, 1144, 1272; now 2 + (layers - 2) grids more).  Bytes.
PROFILE_BASE_BYTES = 64 << 20
FFT_GRIDS_MAX = 36
IMAGE_SUM_ARRAYS = 6
MC_BYTES = 128 << 20


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``profile`` subcommand on an argparse subparsers object."""
    p = subparsers.add_parser("profile", help="layer file of a stack (+ error against Monte Carlo)")
    p.add_argument("layers", help=f"layer TOML file, or a preset name ({', '.join(PRESETS)})")
    p.add_argument("--csv", default=None, help="output CSV path")
    p.add_argument("--mc", type=int, default=0, metavar="PHOTONS",
                   help="also run the OpenCL Monte Carlo with PHOTONS photons per channel "
                        f"(1 .. {MAX_MC_PHOTONS}) and print each model's error against it")
    p.add_argument("--models", default=",".join(MODELS),
                   help=f"models compared with --mc (comma-separated from {', '.join(MODELS)})")
    p.add_argument("--poles", type=int, default=None,
                   help=f"pole pairs n (i = -n..n, 0 .. {MAX_POLES}; default: adaptive)")
    p.add_argument("--seed", type=int, default=0, help=f"Monte Carlo seed (0 .. {MAX_SEED}; the "
                   "monte_carlo model uses seed + 1)")
    p.add_argument("--device", default=None, help="OpenCL device: P:D, P, or a name substring")
    p.set_defaults(func=run)
    return p


def ring_edges(prof) -> np.ndarray:
    """Ring edges (mm) of a layer file: its ``info["r_edges"]`` (Monte Carlo tables), else
    the multipole rings [r_k - h/2, r_k + h/2) with a central disk."""
    if "r_edges" in prof.info:
        return np.asarray(prof.info["r_edges"], np.float64)
    h = float(prof.r_mm[1] - prof.r_mm[0])
    return np.concatenate([[0.0], (np.arange(len(prof.r_mm)) + 0.5) * h])


def ring_energy(prof, edges: np.ndarray, which: str = "R") -> np.ndarray:
    """Energy of ``prof`` between ``edges``, (len-1, 3): its cumulative energy interpolated
    linearly in r^2 (each ring's value is its average density), so exact on its own edges."""
    own = ring_edges(prof)
    X = prof.R if which == "R" else prof.T
    cum = np.vstack([np.zeros(3), np.cumsum(X * (np.pi * np.diff(own**2))[:, None], axis=0)])
    e = np.stack([np.interp(np.asarray(edges) ** 2, own**2, cum[:, c]) for c in range(3)], axis=1)
    return np.diff(e, axis=0)


def _rebin(prof, edges: np.ndarray, key: str) -> np.ndarray:
    """Ring averages (1/mm^2) of a Monte Carlo table on coarser ``edges`` that are a subset of
    its own: sums of its rings (errors in quadrature for keys ending in _err)."""
    own = ring_edges(prof)
    area = np.pi * np.diff(own**2)[:, None]
    idx = np.searchsorted(own, edges)
    if not np.allclose(own[np.minimum(idx, len(own) - 1)], edges):
        raise DermisError("profile: internal: rebinning edges are not a subset")
    if key.endswith("_err"):
        v = np.asarray(prof.info[key[:-4] + "_err"]) ** 2 * area**2
        cum = np.vstack([np.zeros(3), np.cumsum(v, axis=0)])
        return np.sqrt(np.diff(cum[idx], axis=0)) / (np.pi * np.diff(edges**2))[:, None]
    X = prof.R if key == "R" else prof.T
    cum = np.vstack([np.zeros(3), np.cumsum(X * area, axis=0)])
    return np.diff(cum[idx], axis=0) / (np.pi * np.diff(edges**2))[:, None]


def profile_errors(prof, ref, band=ERROR_BAND_MM, rings: int = ERROR_RINGS,
                   field: str = "R") -> dict:
    """Rd, Tt and R(r) (``field="T"``: T(r)) errors of layer file ``prof`` against the Monte
    Carlo ``ref``.

    Returns per channel: dRd, dTt (relative; None where the reference is 0), their reference
    standard errors (relative), and over ``rings`` log-spaced rings in ``band``: the rms and
    the largest relative R(r) error, the radius of the largest, the misplaced energy
    (sum |E - E_ref| / sum E_ref over the rings) and the reference's median relative noise;
    their keys start with ``field`` (``R_misplaced``, ``T_misplaced``, ...).
    The ring edges are moved to the nearest edges of ``prof``'s own rings, and ``ref``
    should hold those edges too (the CLI's reference runs on the union of all rings).
    """
    # log-spaced rings, each edge moved to the nearest ring edge of ``prof`` (a table is not
    # compared below its own resolution: near the source its first ring is a disk)
    own_p = ring_edges(prof)
    edges = np.geomspace(band[0], band[1], rings + 1)
    edges = np.unique(own_p[np.abs(own_p[None, :] - edges[:, None]).argmin(axis=1)])
    edges = edges[edges > 0] if np.sum(edges > 0) > 1 else edges
    mid = np.sqrt(edges[1:] * np.maximum(edges[:-1], 1e-12))
    ep, er = ring_energy(prof, edges, field), ring_energy(ref, edges, field)
    own = ring_edges(ref)
    var = np.vstack([np.zeros(3), np.cumsum((np.asarray(ref.info[f"{field}_err"])
                                             * (np.pi * np.diff(own**2))[:, None]) ** 2, axis=0)])
    ev = np.diff(np.stack([np.interp(edges, own, var[:, c]) for c in range(3)], axis=1), axis=0)
    out = []
    for c in range(3):
        ok = er[:, c] > 0
        rel = np.where(ok, ep[:, c] / np.where(ok, er[:, c], 1.0) - 1.0, np.nan)
        noise = np.where(ok, np.sqrt(ev[:, c]) / np.where(ok, er[:, c], 1.0), np.nan)
        k = int(np.nanargmax(np.abs(rel))) if np.any(ok) else 0
        rd, tt = float(ref.Rd[c]), float(ref.Tt[c])
        tot = float(np.nansum(er[:, c]))
        out.append({
            # energy on the rings put where the reference has none: sum |E - E_ref| / sum E_ref
            f"{field}_misplaced": float(np.nansum(np.abs(ep[:, c] - er[:, c])) / tot)
            if tot > 0 else None,
            "dRd": float(prof.Rd[c] / rd - 1) if rd > 0 else None,
            "dTt": float(prof.Tt[c] / tt - 1) if tt > 0 else None,
            "Rd_se": float(ref.info["Rd_err"][c] / rd) if rd > 0 else None,
            "Tt_se": float(ref.info["Tt_err"][c] / tt) if tt > 0 else None,
            f"{field}_rms": float(np.sqrt(np.nanmean(rel**2))) if np.any(ok) else None,
            f"{field}_max": float(rel[k]) if np.any(ok) else None,
            f"{field}_max_at_mm": float(mid[k]),
            "ref_noise_median": float(np.nanmedian(noise)) if np.any(ok) else None,
        })
    return {"channels": out, "rings_mm": edges.tolist()}


def _pct(x, signed=True) -> str:
    if x is None or not math.isfinite(x):
        return "     -"
    return f"{100 * x:+6.1f}%" if signed else f"{100 * x:5.2f}%"


def check_options(args) -> None:
    """Raise :class:`DermisError` (exit code 2) naming every option outside its bounds: the
    value and what is allowed."""
    problems = []
    poles = getattr(args, "poles", None)
    if poles is not None and not 0 <= poles <= MAX_POLES:
        problems.append(f"--poles = {poles}: must be an integer in 0 .. {MAX_POLES} (pole pairs "
                        "i = -n..n per finite layer; omit it for the adaptive count)")
    mc = getattr(args, "mc", 0)
    if mc and not 1 <= mc <= MAX_MC_PHOTONS:
        problems.append(f"--mc = {mc}: must be a photon count per channel in 1 .. "
                        f"{MAX_MC_PHOTONS} (the bound of [optics] photons; 0 or no --mc: no "
                        "Monte Carlo)")
    seed = getattr(args, "seed", 0)
    if not 0 <= seed <= MAX_SEED:
        problems.append(f"--seed = {seed}: must be an integer in 0 .. {MAX_SEED} (the "
                        "monte_carlo model runs seed + 1)")
    models = [m.strip() for m in str(getattr(args, "models", ",".join(MODELS))).split(",")
              if m.strip()]
    bad = [m for m in models if m not in MODELS]
    if bad:
        problems.append(f"--models: {', '.join(bad)}: unknown; choose from {', '.join(MODELS)}")
    if problems:
        raise DermisError("; ".join(problems))


def estimate_memory(stack: LayerStack, poles: int | None = None,
                    monte_carlo: bool = False) -> list[tuple[str, int]]:
    """Estimated peak bytes of ``dermis profile`` on ``stack``: (what, bytes) parts whose sum
    is the peak (module constants; measured values there)."""
    st = stack.nonzero()
    parts = [("the interpreter, numpy and scipy", PROFILE_BASE_BYTES)]
    if not st.layers:
        return parts
    h, r_max = auto_grid(st)
    n = int(math.ceil(r_max / h))
    if len(st.layers) > 1:
        grids = min(FFT_GRIDS_MAX, 26 + 5 * (len(st.layers) - 2))
        parts.append((f"FFT adding on {grids} grids of {2 * n + 1} x {2 * n + 1}",
                      grids * 8 * (2 * n + 1) ** 2))
    # one image sum: (sources x images) pairs, evaluated over radii in chunks of
    # IMAGE_SUM_CHUNK pairs (one radius at a time beyond); sources as beam_sources allots them
    pairs, most = 0, 0
    for k, lay in enumerate(st.layers):
        for c in range(3):
            ch = diffusion_constants(lay, c, *relative_indices(st, k), "pbd", poles)
            images = 2 * (2 * ch.poles + 1) + (6 if ch.tail else 0)
            sources = max(beam_sources(ch, diffuse=d).t.size for d in (False, True))
            pairs, most = max(pairs, sources * images), max(most, ch.poles)
    radii = 4 * (n + 1) + 128
    what = f"image sums ({most} pole pairs" + (", --poles)" if poles is not None else ")")
    parts.append((what, IMAGE_SUM_ARRAYS * 8 * max(pairs, min(IMAGE_SUM_CHUNK, pairs * radii))))
    if monte_carlo:
        parts.append(("the OpenCL Monte Carlo", MC_BYTES))
    return parts


def _check_memory(stack: LayerStack, src: str, args) -> None:
    """Raise :class:`DermisError` when the estimated peak exceeds the machine's memory."""
    poles, mc = getattr(args, "poles", None), bool(getattr(args, "mc", 0))
    parts = estimate_memory(stack, poles, mc)
    need, have = sum(b for _, b in parts), machine_memory()
    if need <= have:
        return
    detail = ", ".join(f"{what}: {b / 2**30:.2f} GiB" for what, b in parts)
    fits = [hint for hint, p, m in (("omit --poles (the adaptive pole count fits)", None, mc),
                                    ("omit --mc", poles, False))
            if (p, m) != (poles, mc) and sum(b for _, b in estimate_memory(stack, p, m)) <= have]
    hint = " or ".join(fits) if fits else "the stack's own grid and images need it"
    raise DermisError(f"profile {src}: needs about {need / 2**30:.2f} GiB at its peak ({detail}); "
                      f"this machine has {have / 2**30:.2f} GiB (${MEMORY_ENV_VAR} overrides): "
                      + hint)


def run(args) -> int:
    """Execute ``dermis profile``; returns the exit code."""
    # the layer-file library (scipy, ~0.5 s to import) is loaded when the command runs, not
    # when ``dermis`` builds its parser
    from dermis.optics.layer_profiles import MultipoleOptions, build_profiles
    from dermis.optics.monte_carlo_table import mc_bin_edges, monte_carlo_profiles

    check_options(args)
    src = args.layers
    stack = PRESETS[src] if src in PRESETS and not Path(src).exists() else load_layers_toml(src)
    _check_memory(stack, src, args)
    prof = build_profiles(stack, options=MultipoleOptions(poles=getattr(args, "poles", None)))
    r = prof.r_mm
    cols = {"r_mm": r}
    for i, c in enumerate("rgb"):
        cols[f"R_{c}"] = prof.R[:, i]
    for i, c in enumerate("rgb"):
        cols[f"T_{c}"] = prof.T[:, i]
    mc = None
    models = [m.strip() for m in str(getattr(args, "models", ",".join(MODELS))).split(",") if m.strip()]
    if args.mc:
        env = dcl.get_env(getattr(args, "device", None))
        # the reference runs on the union of the layer-file rings, the Monte Carlo table's
        # rings (fine near the source) and the error rings, so every rebinning is exact
        edges = ring_edges(prof)
        mc_edges = mc_bin_edges(stack)
        union = np.unique(np.concatenate([edges, mc_edges]))
        union = union[union <= max(edges[-1], mc_edges[-1])]
        mc = monte_carlo_profiles(stack, photons=args.mc, seed=args.seed, env=env, edges=union)
        for name, key in (("MC_R", "R"), ("MC_T", "T")):
            a = _rebin(mc, edges, key)
            for i, c in enumerate("rgb"):
                cols[f"{name}_{c}"] = a[:, i]
        for name, key in (("MC_R", "R_err"), ("MC_T", "T_err")):
            a = _rebin(mc, edges, key)
            for i, c in enumerate("rgb"):
                cols[f"{name}_{c}_err"] = a[:, i]
    if args.csv:
        out = Path(args.csv)
        out.parent.mkdir(parents=True, exist_ok=True)
        data = np.column_stack(list(cols.values()))
        header = (f"# dermis profile {src}: R, T ring averages in 1/mm^2 (rings [r - h/2, r + h/2), "
                  f"a disk at r = 0; integral 2 pi r R dr = Rd) per photon that entered the top "
                  f"surface (specular reflection at entry not counted; x (1 - R_sp) for per "
                  f"incident photon); Rd = {_vec(prof.Rd)}, Tt = {_vec(prof.Tt)} (multipole)"
                  + (f"; MC Rd = {_vec(mc.Rd)}, Tt = {_vec(mc.Tt)}, {mc.info['photons']} "
                     f"photons per channel, seed {args.seed}" if mc is not None else "")
                  + "\n" + ",".join(cols))
        np.savetxt(out, data, delimiter=",", header=header, comments="", fmt="%.9g")
    for i, c in enumerate(("red", "green", "blue")):
        print(f"{c} {prof.Rd[i]:.6f} {prof.Tt[i]:.6f}")
    if mc is None:
        return 0
    _report(stack, prof, mc, models, args, env)
    return 0


def _vec(v) -> str:
    return "(" + ", ".join(f"{float(x):.5f}" for x in v) + ")"


def _report(stack, prof, mc, models, args, env) -> None:
    from dermis.optics.layer_profiles import MultipoleOptions, build_profiles  # as in run()
    from dermis.optics.monte_carlo_table import mc_bin_edges, monte_carlo_profiles

    r_sp = fresnel_normal(stack.layers[0].eta / stack.eta_above)
    i = mc.info
    print(f"\nR, T per photon entering the top surface (specular reflection at entry, "
          f"R_sp = {r_sp:.5f}, not counted; per incident photon: x {1 - r_sp:.5f})")
    print(f"Monte Carlo reference: {i['photons']} photons per channel, seed {args.seed}, "
          f"{i['kernel_seconds']:.1f} s kernel ({i['photons_per_second']:,.0f} photons/s), "
          f"{i['device']}")
    print(f"  Rd {_vec(mc.Rd)} +- {_vec(i['Rd_err'])}   Tt {_vec(mc.Tt)} +- {_vec(i['Tt_err'])}")
    built = {"multipole": prof}
    for m in models:
        if m in built:
            continue
        if m == "diffusion":
            built[m] = build_profiles(stack, options=MultipoleOptions(totals="diffusion",
                                                                      poles=args.poles))
        elif m == "dj2005":
            built[m] = build_profiles(stack, options=MultipoleOptions(diffusion="dj2005",
                                                                      poles=args.poles))
        elif m == "monte_carlo":
            built[m] = monte_carlo_profiles(stack, photons=args.mc, seed=args.seed + 1,
                                            env=env, edges=mc_bin_edges(stack))
    lo, hi = ERROR_BAND_MM
    print(f"\n{'model':<12} {'ch':<5} {'Rd':>8} {'dRd':>7} {'(MC se)':>8} {'Tt':>8} {'dTt':>7} "
          f"{'(MC se)':>8}   R(r) over [{lo:g}, {hi:g}] mm: misplaced energy, rms, largest (at r), "
          f"MC noise")
    for m in models:
        p = built[m]
        err = profile_errors(p, mc)
        for c, ch in enumerate(("red", "green", "blue")):
            e = err["channels"][c]
            at = f"{e['R_max_at_mm']:.2f} mm"
            print(f"{m:<12} {ch:<5} {p.Rd[c]:8.5f} {_pct(e['dRd'])} ({_pct(e['Rd_se'], False)}) "
                  f"{p.Tt[c]:8.5f} {_pct(e['dTt'])} ({_pct(e['Tt_se'], False)})   "
                  f"{_pct(e['R_misplaced'], False)}, {_pct(e['R_rms'], False)}, "
                  f"{_pct(e['R_max'])} (at {at}), {_pct(e['ref_noise_median'], False)}")
    lobes = prof.info.get("negative_lobes", [])
    if lobes:
        print(f"\nmultipole: {len(lobes)} negative lobe(s) removed (energy kept):")
        for lb in lobes[:6]:
            print(f"  layer {lb.get('layer')} {lb.get('light', lb.get('dir', ''))} {lb['field']} "
                  f"{lb['channel']}: r {lb['r_mm'][0]:.2f}-{lb['r_mm'][1]:.2f} mm, "
                  f"{100 * lb['energy_fraction']:.3g} % of its energy")


def main(argv=None) -> int:  # pragma: no cover - convenience for running this file alone
    ap = argparse.ArgumentParser(prog="dermis")
    add_parser(ap.add_subparsers(dest="cmd", required=True))
    args = ap.parse_args(argv)
    try:
        return args.func(args)
    except DermisError as exc:
        print(f"dermis: error: {exc}")
        return exc.exit_code
