"""``dermis profile LAYERS.toml --csv OUT.csv [--mc PHOTONS]``: build a layer file.

Interface kept stable (other tools call it).  The CSV has ``r_mm,R_r,R_g,R_b,T_r,T_g,T_b``
(1/mm^2, ring averages, integral 2 pi r R dr = Rd), plus with ``--mc`` the Monte Carlo
columns ``MC_R_*``, ``MC_T_*`` and ``MC_R_*_err``, ``MC_T_*_err`` on the same rings.  One
line per channel is printed: ``channel Rd Tt`` (multipole) and, with ``--mc``, the Monte
Carlo totals with standard errors.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dermis.pipeline.errors import DermisError
from dermis.physics.layers import PRESETS, load_layers_toml

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``profile`` subcommand on an argparse subparsers object."""
    p = subparsers.add_parser("profile", help="multipole layer file (+ Monte Carlo reference)")
    p.add_argument("layers", help=f"layer TOML file, or a preset name ({', '.join(PRESETS)})")
    p.add_argument("--csv", required=True, help="output CSV path")
    p.add_argument("--mc", type=int, default=0, metavar="PHOTONS",
                   help="also run the OpenCL Monte Carlo with PHOTONS photons per channel")
    p.add_argument("--poles", type=int, default=None, help="pole pairs n (i = -n..n)")
    p.add_argument("--seed", type=int, default=0, help="Monte Carlo seed")
    p.add_argument("--device", default=None, help="OpenCL device: P:D, P, or a name substring")
    p.set_defaults(func=run)
    return p


def _mc_on_rings(mc, n: int):
    """Rebin MC rings of width h/2 from 0 onto the layer-file rings [kh - h/2, kh + h/2)."""
    e = mc.R * (np.pi * np.diff(mc.r_edges**2))[:, None]
    et = mc.T * (np.pi * np.diff(mc.r_edges**2))[:, None]
    ve = (mc.R_err * (np.pi * np.diff(mc.r_edges**2))[:, None]) ** 2
    vt = (mc.T_err * (np.pi * np.diff(mc.r_edges**2))[:, None]) ** 2
    out = []
    for a in (e, et, ve, vt):
        b = np.zeros((n + 1, 3))
        b[0] = a[0]
        b[1:] = a[1:2 * n:2] + a[2:2 * n + 1:2]
        out.append(b)
    return out


def run(args) -> int:
    """Execute ``dermis profile``; returns the exit code."""
    from dermis.stages import profiles

    src = args.layers
    stack = PRESETS[src] if src in PRESETS and not Path(src).exists() else load_layers_toml(src)
    prof = profiles.build_profiles(stack, poles=getattr(args, "poles", None))
    r = prof.r_mm
    cols = {"r_mm": r}
    for i, c in enumerate("rgb"):
        cols[f"R_{c}"] = prof.R[:, i]
    for i, c in enumerate("rgb"):
        cols[f"T_{c}"] = prof.T[:, i]
    mc = None
    if args.mc:
        from dermis.stages import mc_slab
        from dermis.pipeline import cl as dcl
        if args.mc < 1:
            raise DermisError(f"--mc = {args.mc}: must be a positive photon count")
        h = r[1] - r[0]
        n = len(r) - 1
        mc = mc_slab.simulate(stack, photons=args.mc, r_max_mm=(2 * n + 1) * h / 2,
                         bins=2 * n + 1, seed=args.seed,
                         env=dcl.get_env(getattr(args, "device", None)))
        e, et, ve, vt = _mc_on_rings(mc, n)
        area = np.pi * np.diff(np.concatenate([[0.0], (np.arange(n + 1) + 0.5) * h]) ** 2)
        for name, a in (("MC_R", e), ("MC_T", et)):
            for i, c in enumerate("rgb"):
                cols[f"{name}_{c}"] = a[:, i] / area
        for name, a in (("MC_R", ve), ("MC_T", vt)):
            for i, c in enumerate("rgb"):
                cols[f"{name}_{c}_err"] = np.sqrt(a[:, i]) / area
    out = Path(args.csv)
    out.parent.mkdir(parents=True, exist_ok=True)
    data = np.column_stack(list(cols.values()))
    np.savetxt(out, data, delimiter=",", header=",".join(cols), comments="", fmt="%.9g")
    for i, c in enumerate(("red", "green", "blue")):
        print(f"{c} {prof.Rd[i]:.6f} {prof.Tt[i]:.6f}")
    if mc is not None:
        for i, c in enumerate(("red", "green", "blue")):
            print(f"{c} MC {mc.Rd[i]:.6f} +- {mc.Rd_err[i]:.6f} {mc.Tt[i]:.6f} +- {mc.Tt_err[i]:.6f}")
    return 0


def main(argv=None) -> int:  # pragma: no cover - convenience for running this file alone
    ap = argparse.ArgumentParser(prog="dermis")
    add_parser(ap.add_subparsers(dest="cmd", required=True))
    args = ap.parse_args(argv)
    try:
        return args.func(args)
    except DermisError as exc:
        print(f"dermis: error: {exc}")
        return exc.exit_code
