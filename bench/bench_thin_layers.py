"""Thin layers: where the multipole layer file puts R and T against dermis's own Monte Carlo.

Usage: python bench/bench_thin_layers.py --label NAME [--out bench/results/thin_layers.json]
       [--photons N] [--cases a,b,...]
       python bench/bench_thin_layers.py --images BEFORE_CACHE AFTER_CACHE --label NAME

The second form compares the BSSRDF images of two runs of a scene (``dermis run SCENE
--cache DIR`` before and after a change): per render node, the relative RMSE, the change of
the mean per channel, the largest |difference| over the image's peak and whether the bytes
are equal; every other data array is checked for equality.

For each case (scenes/layers/<case>.toml) and channel, the multipole layer file (the
BSSRDF's default) against a Monte Carlo table (seed 1, ``--photons`` per channel on average,
radial splitting) on the union of both tables' rings, for R and T:

* ``misplaced``, ``rms``, ``max``: over 24 log rings in [0.05, 5] mm
  (optics/profile_command.py ``profile_errors``): sum |E - E_MC| / sum E_MC, rms and largest
  relative ring error;
* ``rings``: the relative error of the energy on the rings [0, 0.05, 0.1, 0.2, 0.5, 1, 2, 5]
  mm and the Monte Carlo's relative standard error on each;
* ``frac_0.05_2``: the fraction of the total (Rd or Tt) on [0.05, 2] mm, model and Monte
  Carlo (with its standard error).

The results of each ``--label`` are kept side by side in the output file (``before`` is the
multipole that puts the light a thin layer passes on as a delta at r = 0).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dermis.optics.layers import load_layers_toml  # noqa: E402
from dermis.optics.layer_file import RD_CONVENTION  # noqa: E402
from dermis.optics.layer_profiles import build_profiles  # noqa: E402
from dermis.optics.monte_carlo_table import mc_bin_edges, monte_carlo_profiles  # noqa: E402
from dermis.optics.profile_command import profile_errors, ring_edges, ring_energy  # noqa: E402

CASES = ("thin_epidermis", "thin_epidermis_from_below", "two_layer_skin", "two_layer", "skin1")
COARSE = np.array([0.0, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0])
BAND = (0.05, 2.0)


def ring_se(ref, edges: np.ndarray, field: str) -> np.ndarray:
    """(len(edges)-1, 3) standard errors of the reference's energy on ``edges`` (edges of its
    own rings: the per-ring errors added in quadrature)."""
    own = ring_edges(ref)
    var = np.vstack([np.zeros(3), np.cumsum((np.asarray(ref.info[f"{field}_err"])
                                             * (np.pi * np.diff(own**2))[:, None]) ** 2, axis=0)])
    idx = np.searchsorted(own, edges)
    assert np.allclose(own[idx], edges), "the reference must hold the comparison edges"
    return np.sqrt(np.diff(var[idx], axis=0))


def field_report(prof, ref, field: str) -> dict:
    tot_p = prof.Rd if field == "R" else prof.Tt
    tot_r = ref.Rd if field == "R" else ref.Tt
    if not np.any(tot_r > 0):
        return {}
    err = profile_errors(prof, ref, field=field)
    ep, er = ring_energy(prof, COARSE, field), ring_energy(ref, COARSE, field)
    se = ring_se(ref, COARSE, field)
    band = [np.searchsorted(COARSE, BAND[0]), np.searchsorted(COARSE, BAND[1])]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(er > 0, ep / er - 1.0, np.nan)
        rel_se = np.where(er > 0, se / er, np.nan)
    fp = ep[band[0]:band[1]].sum(axis=0) / tot_p
    fr = er[band[0]:band[1]].sum(axis=0) / tot_r
    fr_se = np.sqrt((se[band[0]:band[1]] ** 2).sum(axis=0)) / tot_r
    ch = err["channels"]
    return {"misplaced": [c[f"{field}_misplaced"] for c in ch],
            "rms": [c[f"{field}_rms"] for c in ch],
            "max": [c[f"{field}_max"] for c in ch],
            "max_at_mm": [c[f"{field}_max_at_mm"] for c in ch],
            "total_rel": (tot_p / tot_r - 1.0).tolist(),
            "rings_mm": COARSE.tolist(), "rings_rel": np.round(rel.T, 4).tolist(),
            "rings_mc_se": np.round(rel_se.T, 4).tolist(),
            f"frac_{BAND[0]}_{BAND[1]}": {"model": fp.tolist(), "mc": fr.tolist(),
                                          "mc_se": fr_se.tolist()}}


def compare_images(before: Path, after: Path) -> dict:
    """BSSRDF image changes between two caches of the same scene (module notes)."""
    out: dict = {"render": {}, "other_arrays_equal": [], "other_arrays_changed": []}
    for node in sorted(p for p in after.iterdir() if p.is_dir()):
        fa = sorted(node.glob("*/data.npz"))
        fb = sorted((before / node.name).glob("*/data.npz"))
        if not fa or not fb:
            continue
        a, b = np.load(fa[0]), np.load(fb[0])
        if node.name.startswith("render-bssrdf"):
            la, lb = a["linear"].astype(np.float64), b["linear"].astype(np.float64)
            m = a["mask"] & b["mask"]
            d, ref = (la - lb)[m], lb[m]
            out["render"][node.name] = {
                "rel_rmse": float(np.sqrt(np.mean(d**2)) / np.sqrt(np.mean(ref**2))),
                "mean_rel": (la[m].mean(axis=0) / lb[m].mean(axis=0) - 1.0).tolist(),
                "max_abs_over_peak": float(np.abs(d).max() / ref.max()),
                "bytes_equal": bool(np.array_equal(a["linear"], b["linear"]))}
            continue
        same = a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
        out["other_arrays_equal" if same else "other_arrays_changed"].append(node.name)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--label", required=True)
    ap.add_argument("--images", nargs=2, metavar=("BEFORE_CACHE", "AFTER_CACHE"))
    ap.add_argument("--out", default=str(ROOT / "bench/results/thin_layers.json"))
    ap.add_argument("--photons", type=int, default=2_000_000, help="MC photons per channel")
    ap.add_argument("--cases", default=",".join(CASES))
    args = ap.parse_args()
    path = Path(args.out)
    out = json.loads(path.read_text()) if path.exists() else {}
    if args.images:
        res = compare_images(Path(args.images[0]), Path(args.images[1]))
        out.setdefault("images", {})[args.label] = res
        for name, r in res["render"].items():
            print(f"{name:50s} rel RMSE {r['rel_rmse']:.2e} max |d|/peak "
                  f"{r['max_abs_over_peak']:.2e}")
        print("changed:", res["other_arrays_changed"])
        path.write_text(json.dumps(out, indent=1))
        return
    out.setdefault("convention", RD_CONVENTION)
    out.setdefault("mc", {})
    res = out.setdefault(args.label, {})
    res["load_average_start"] = os.getloadavg()
    for name in args.cases.split(","):
        st = load_layers_toml(ROOT / "scenes/layers" / f"{name}.toml")
        t = time.perf_counter()
        prof = build_profiles(st)
        build_s = time.perf_counter() - t
        edges = ring_edges(prof)
        mc_edges = mc_bin_edges(st)
        union = np.unique(np.concatenate([edges, mc_edges, COARSE]))
        union = union[union <= max(edges[-1], mc_edges[-1])]
        t = time.perf_counter()
        ref = monte_carlo_profiles(st, photons=args.photons, seed=1, edges=union)
        out["mc"][name] = {"photons_per_channel": ref.info["photons_per_channel"],
                           "Rd": ref.Rd.tolist(), "Rd_err": ref.info["Rd_err"],
                           "Tt": ref.Tt.tolist(), "Tt_err": ref.info["Tt_err"],
                           "wall_s": time.perf_counter() - t}
        entry = {"build_s": build_s, "T_ballistic": prof.info["T_ballistic"],
                 "T_forward": prof.info["T_forward"],
                 "negative_lobes": len(prof.info.get("negative_lobes", []))}
        for field in "RT":
            entry[field] = field_report(prof, ref, field)
            if entry[field]:
                f = entry[field]
                print(f"{name:26s} {field} misplaced {_fmt(f['misplaced'])} on "
                      f"[0, .05) {_fmt([r[0] for r in f['rings_rel']])} frac[.05, 2] "
                      f"{np.round(f['frac_0.05_2.0']['model'], 3)} MC "
                      f"{np.round(f['frac_0.05_2.0']['mc'], 3)}")
        res[name] = entry
    res["load_average_end"] = os.getloadavg()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


def _fmt(v) -> str:
    return "[" + " ".join("    -" if x is None else f"{100 * x:+5.1f}" for x in v) + "] %"


if __name__ == "__main__":
    main()
