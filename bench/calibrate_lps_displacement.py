"""Calibrate the displacement scale (mm per unit) and neutral level of the LPS displacement JPEG.

The 8-bit map lost the original's absolute scale and neutral level (lps_head README).  Two
independent measurements, both on the 17,684-triangle base mesh subdivided 3x with Loop
(1,131,776 triangles, what ``make_high`` builds):

A. Base-vertex regression (primary).  The base mesh's own vertices lie on the scanned surface,
   while the Loop surface shrinks away from them; a displacement map baked against the smoothed
   surface must restore them.  At every base vertex fit  (v_base - v_loop) . n_loop = s * (d - mid)
   by least squares: slope s [mm] and intercept give both the scale and the neutral level, and the
   correlation says whether the model holds.
B. Normal-map agreement (cross-check, the README's suggestion).  Displace at candidate scales,
   express the displaced vertex normals in the base surface's UV tangent frame (T = dp/du,
   B = dp/dv, Gram-Schmidt against N) and compare with Infinite-Level_02_Tangent_SmoothUV.jpg
   (rgb -> 2c - 1, both green-channel conventions tried).  The map is box-filtered 4096 -> 1024 to
   the normal map's resolution for this, so aliasing at the ~0.8 mm vertex spacing does not bias
   the fit.  Mean angle vs scale; the minimum should sit near A's scale.

Run: python bench/calibrate_lps_displacement.py [--out bench/results/lps_displacement_calibration.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "lps_head"

from dermis.geometry.scan import load_scan, read_grey_image  # noqa: E402
from dermis.geometry.subdivision import make_high, sample_image, vertex_uv_pairs  # noqa: E402
from dermis.geometry.validation import validate  # noqa: E402


def vertex_samples(mesh, image):
    """Per-vertex mean of the image over the vertex's UVs, and whether the vertex has a single UV."""
    f = mesh.faces.astype(np.int64)
    pv, pt = vertex_uv_pairs(f, mesh.uv_faces.astype(np.int64), len(mesh.uv))
    s = sample_image(image, mesh.uv[pt])
    cnt = np.bincount(pv, minlength=len(mesh.vertices))
    if s.ndim == 1:
        out = np.bincount(pv, weights=s, minlength=len(mesh.vertices)) / np.maximum(cnt, 1)
    else:
        out = np.stack([np.bincount(pv, weights=s[:, c], minlength=len(mesh.vertices)) for c in range(s.shape[1])], 1)
        out /= np.maximum(cnt, 1)[:, None]
    return out, cnt == 1


def tangent_frames(mesh):
    """Per-vertex (T, B, N) from the UV Jacobian of incident faces (area-weighted), Gram-Schmidt on N."""
    v, f = mesh.vertices, mesh.faces.astype(np.int64)
    uv, uvf = mesh.uv.astype(np.float64), mesh.uv_faces.astype(np.int64)
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    d1, d2 = uv[uvf[:, 1]] - uv[uvf[:, 0]], uv[uvf[:, 2]] - uv[uvf[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    det = np.where(np.abs(det) < 1e-20, 1e-20, det)
    T = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    B = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / det[:, None]
    n = mesh.normals.astype(np.float64)
    Tv = np.stack([np.bincount(f.ravel(), weights=np.repeat(T[:, k], 3), minlength=len(v)) for k in range(3)], 1)
    Bv = np.stack([np.bincount(f.ravel(), weights=np.repeat(B[:, k], 3), minlength=len(v)) for k in range(3)], 1)
    Tv -= n * np.sum(Tv * n, 1, keepdims=True)
    Tv /= np.maximum(np.linalg.norm(Tv, axis=1, keepdims=True), 1e-20)
    Bv -= n * np.sum(Bv * n, 1, keepdims=True) + Tv * np.sum(Bv * Tv, 1, keepdims=True)
    Bv /= np.maximum(np.linalg.norm(Bv, axis=1, keepdims=True), 1e-20)
    return Tv, Bv, n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "lps_displacement_calibration.json"))
    args = ap.parse_args()
    if not DATA.is_dir():
        print(f"skip: {DATA} not found")
        return 0
    t0 = time.perf_counter()
    base, _ = validate(load_scan(DATA / "LeePerrySmith_cm.obj", units="cm"), source="lps")
    disp = read_grey_image(DATA / "Infinite-Level_02_Disp_NoSmoothUV-4096.jpg")
    import OpenImageIO as oiio
    nm = np.asarray(oiio.ImageBuf(str(DATA / "Infinite-Level_02_Tangent_SmoothUV.jpg")).get_pixels(oiio.FLOAT))[:, :, :3]
    result: dict = {"map_min": float(disp.min()), "map_max": float(disp.max()), "map_median": float(np.median(disp))}

    # A. base-vertex regression at 1, 2, 3 Loop splits
    reg = {}
    nb = len(base.vertices)
    for k in (1, 2, 3):
        smooth = make_high(base, target_triangles=len(base.faces) * 4 ** k - 1)
        delta = np.einsum("ij,ij->i", base.vertices - smooth.vertices[:nb], smooth.normals[:nb].astype(np.float64))
        dv, _ = vertex_samples(smooth, disp)
        dv = dv[:nb]
        (s, c), *_ = np.linalg.lstsq(np.stack([dv, np.ones(nb)], 1), delta, rcond=None)
        resid = delta - (s * dv + c)
        reg[k] = {"scale_mm": float(s), "mid": float(-c / s), "corr": float(np.corrcoef(dv, delta)[0, 1]),
                  "rms_residual_mm": float(np.sqrt(np.mean(resid ** 2))), "rms_delta_mm": float(np.sqrt(np.mean(delta ** 2)))}
        print(f"A: {k} Loop splits: scale {s:.3f} mm, mid {-c / s:.4f}, corr {reg[k]['corr']:.4f}, "
              f"rms residual {reg[k]['rms_residual_mm']:.3f} of {reg[k]['rms_delta_mm']:.3f} mm")
    result["regression"] = reg
    scale_a, mid_a = reg[3]["scale_mm"], reg[3]["mid"]

    # B. normal-map agreement at candidate scales (3 splits, map box-filtered to 1024)
    h, w = disp.shape
    f4 = h // nm.shape[0]
    disp_lo = disp.reshape(h // f4, f4, w // f4, f4).mean(axis=(1, 3))
    smooth = make_high(base, target_triangles=len(base.faces) * 64 - 1)
    T, B, N = tangent_frames(smooth)
    nmv, single = vertex_samples(smooth, nm)
    target = 2.0 * nmv - 1.0
    target /= np.maximum(np.linalg.norm(target, axis=1, keepdims=True), 1e-12)
    curve = {}
    for scale in [0.0, 2.0, 4.0, 5.0, 6.0, 6.5, 7.0, 8.0, 10.0, 12.0]:
        hm = make_high(base, target_triangles=len(base.faces) * 64 - 1, displacement=disp_lo,
                       displacement_scale_mm=scale, displacement_mid=mid_a)
        n = hm.normals.astype(np.float64)
        loc = np.stack([np.sum(n * T, 1), np.sum(n * B, 1), np.sum(n * N, 1)], 1)
        errs = {}
        for gname, gsign in (("green_up", 1.0), ("green_down", -1.0)):
            tgt = target * np.array([1.0, gsign, 1.0])
            cosang = np.clip(np.sum(loc[single] * tgt[single], 1), -1, 1)
            errs[gname] = float(np.degrees(np.arccos(cosang)).mean())
        curve[scale] = errs
        print(f"B: scale {scale:5.2f} mm: mean angle to normal map {errs['green_up']:.3f} deg (green up), "
              f"{errs['green_down']:.3f} deg (green down)")
    best_conv = min(("green_up", "green_down"), key=lambda g: min(c[g] for c in curve.values()))
    best_b = min(curve, key=lambda s: curve[s][best_conv])
    result["normal_map"] = {"curve_deg": {str(k): v for k, v in curve.items()}, "convention": best_conv,
                            "best_scale_mm": best_b}
    result["chosen"] = {"scale_mm": round(scale_a, 2), "mid": round(mid_a, 4), "method": "A (regression, 3 Loop splits)"}
    result["seconds"] = time.perf_counter() - t0
    print(f"chosen: LPS_DISPLACEMENT_SCALE_MM = {scale_a:.2f}, LPS_DISPLACEMENT_MID = {mid_a:.4f}; "
          f"normal-map best {best_b} mm ({best_conv})")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
