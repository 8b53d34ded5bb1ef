"""The interactive comparison page of the default run: its size, how long the report stage
takes to write it, and how long Chromium takes to open it.

Runs the default scene (every stage cached in ``--cache`` is reused; the report node is
recomputed, with :func:`dermis.reports.interactive_page.write_page` timed) and opens the
page it wrote in headless Chromium (Debian's ``chromium`` driven by Playwright): time to the
first paint of the grid (DOMContentLoaded), to the ``load`` event (every data block
parsed), and from a click on the first image to its comparator with both images decoded
and drawn.  ``--page`` measures an existing page instead (no run, no write time).
Writes ``bench/results/report_page.json``.

    python3 bench/bench_report_page.py [--cache DIR] [--page out/default/report/report.html]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
RESULT = REPO / "bench" / "results" / "report_page.json"
REPEATS = 3   # page openings timed (the median is reported)


def run_default(cache: str) -> tuple[Path, float]:
    """The default run with the report recomputed: (its page, seconds write_page took)."""
    from dermis.reports import interactive_page
    took = []
    real = interactive_page.write_page

    def timed(*a, **k):
        t = time.perf_counter()
        out = real(*a, **k)
        took.append(time.perf_counter() - t)
        return out
    interactive_page.write_page = timed          # before the report stage imports it
    from dermis.pipeline.api import load_scene, run
    from dermis.pipeline.config import default_scene_path
    summary = run(load_scene(default_scene_path()), cache=cache, force=["report"], export=False)
    report = next(n for n in summary.nodes if n.id == "report")
    return Path(report.path) / interactive_page.PAGE, took[0]


def sizes(page: Path) -> dict:
    html = page.read_text(encoding="utf-8")
    man = re.search(r'<script type="application/json" id="manifest">(.*?)</script>', html, re.S)
    blocks = re.findall(r'<script type="application/x-dermis-data" id="d-([^"]+)">([^<]*)',
                        html)
    images = [b for k, b in blocks if k.startswith("i")]
    manifest = json.loads(man.group(1))
    thumbs = sum(len(e.get("thumb", "")) for e in manifest["images"])
    return {"page_bytes": page.stat().st_size, "manifest_bytes": len(man.group(1)),
            "thumbnail_bytes": thumbs, "data_bytes": sum(len(b) for _, b in blocks),
            "images": len(manifest["images"]),
            "image_block_bytes_mean": statistics.mean(len(b) for b in images),
            "pixels": sum(e["width"] * e["height"] for e in manifest["images"])}


def browser_times(page: Path) -> dict:
    from playwright.sync_api import sync_playwright
    exe = shutil.which("chromium")
    out = {"dom_content_loaded_s": [], "load_s": [], "open_comparator_s": []}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=["--no-sandbox"])
        version = browser.version
        for _ in range(REPEATS):
            tab = browser.new_page(viewport={"width": 1600, "height": 1000})
            tab.goto(page.resolve().as_uri(), wait_until="load")
            nav = tab.evaluate("JSON.stringify(performance.getEntriesByType('navigation')[0])")
            nav = json.loads(nav)
            out["dom_content_loaded_s"].append(nav["domContentLoadedEventEnd"] / 1000)
            out["load_s"].append(nav["loadEventEnd"] / 1000)
            t = time.perf_counter()
            tab.locator("#grid .card").first.click()
            tab.wait_for_function("window.dermis.ready")
            out["open_comparator_s"].append(time.perf_counter() - t)
            tab.close()
        browser.close()
    med = {k: statistics.median(v) for k, v in out.items()}
    return {"chromium": version, "repeats": REPEATS, "median": med, "all": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/dermis-bench-report-page")
    ap.add_argument("--page", default=None, help="measure this page (no run)")
    args = ap.parse_args(argv)
    write_s, load_before = None, os.getloadavg()
    if args.page:
        page = Path(args.page)
    else:
        page, write_s = run_default(args.cache)
    result = {"what": "report.html of the default scene (scenes/default.toml)",
              "host": {"cpu_count": os.cpu_count(), "machine": platform.machine(),
                       "python": platform.python_version(),
                       # other jobs share the machine: its 1-minute load before and after
                       "load_average_1min": [load_before[0], os.getloadavg()[0]]},
              "write_page_s": write_s, "sizes": sizes(page), "browser": browser_times(page)}
    RESULT.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
