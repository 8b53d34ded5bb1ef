"""HK93 under the sunset at g = 0.8 and -0.99 (tests/test_hardening.py test23's scene: the
quick procedural head, 128 x 128): max, 99th percentile, mean, and the fraction of head
pixels above 5x their 3x3 median (outliers): the before/after numbers of
bench/results/hk93_retro.json (the retro lobe, lighting/lobes.py RetroLobe; docs/hardening.md).

Usage: python bench/bench_hk93_retro.py WORKDIR [LABEL]   (merges LABEL into the JSON)"""
import sys, json, os, time
REPO = __import__("pathlib").Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
import numpy as np
from pathlib import Path
from scipy.ndimage import median_filter
from test_hardening import scene_file, _two_layer, main
from dermis.pipeline.imageio import read_image
from labelled import save_labelled
root = Path(sys.argv[1]); root.mkdir(exist_ok=True)
cache = root / "cache"
out = {"loadavg": os.getloadavg()}
for g in (0.8, -0.99):
    s = scene_file(root, {"render": {"models": ["hk93"], "lights": ["sunset"]},
                          "camera": {"width": 128, "height": 128}, "optics": _two_layer(g)}, f"g{g}.toml")
    t0 = time.perf_counter()
    assert main(["run", str(s), "--cache", str(cache), "-q"]) == 0
    img = read_image(root / "out" / "quick" / "render" / "hk93-sunset-high.exr")
    lum = img[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    head = lum > 0
    med = median_filter(lum, 3)
    out[str(g)] = {"max": float(img.max()), "p99": float(np.percentile(img, 99)),
                   "p99_head_lum": float(np.percentile(lum[head], 99)),
                   "outliers_5x_median3": float(((lum > 5 * med) & head).sum() / head.sum()),
                   "mean_rgb": img[..., :3].mean(axis=(0, 1)).round(5).tolist(),
                   "seconds": time.perf_counter() - t0}
out["loadavg_end"] = os.getloadavg()
print(json.dumps(out, indent=1))
if len(sys.argv) > 2:
    save_labelled(REPO / "bench" / "results" / "hk93_retro.json", sys.argv[2], out)
