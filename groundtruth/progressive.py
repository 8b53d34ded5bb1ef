"""Progressive reference rendering: two half-buffers, only the head's pixels, samples sent
where the report's measures are still noisy, until they reach their target or the time runs out.

The report compares models with the reference on face-region means and on block means
(:mod:`dermis.reports.ground_truth`).  A whole-frame render spends most of its samples where
they are not needed: half the frame misses the head, and the small regions (nose, ear) need
tens of times more samples per pixel than the large ones for the same standard error of
their mean.  So the reference is rendered in passes (docs/ground-truth.md):

* **Two half-buffers.**  Every sample batch is traced twice with independent seeds, once
  into half A and once into half B, with the same samples per pixel: the image is
  (A + B) / 2 and (A - B) / 2 estimates its per-pixel error (:mod:`dermis.groundtruth.noise`).
* **Only the head.**  Paths start only at pixels whose centre ray hits the head
  (:func:`dermis.groundtruth.passes.pixel_hits`), traced by
  :func:`dermis.groundtruth.pixel_tracing.trace_pixels`.
* **Uniform, then adaptive.**  Passes first bring every head pixel to ``min_spp`` samples
  per half (the block noise the ranking needs).  Then each pass serves only the face
  regions whose luminance mean still has a relative standard error above the target (the
  worst first: those within a factor 2 of the worst region's error): a
  region at relative error s with n samples per pixel needs n (s / target)^2; a pass adds
  that many, at least ``pass_spp`` and at most doubling n (the estimate of s is itself noisy
  at small n), never beyond ``max_spp``.  The passes are chosen from the buffers alone, so
  they are the same on every machine.
* **Required, then refined.**  The passes first bring every region to ``required_rel_se``
  (aiming at it, so by the fewest paths), whatever the clock says: only a hard cap on paths
  (``max_paths``) or passes stops them earlier.  Then they aim at ``target_rel_se`` while
  the rendering seconds stay within ``budget_s``.  The guaranteed part is the same passes and
  the same bytes on a loaded machine as on an idle one; only how far the refinement gets
  depends on the clock.
* **Tasks.**  A pass is a list of tasks: tiles of at most :data:`TILE_PIXELS` pixels times
  chunks of their samples of about :data:`TASK_PATHS` paths per half, each traced with its
  own seed, derived from (seed, pass, task, half) alone.  The tasks of a pass are independent
  (:func:`render_pass` takes any way of tracing a list of them: serially, or on Dask
  workers through ``pipeline/taskpool.py``), and their sums are added in
  tile order, so the buffers are the same bytes for any number of workers.

Everything needed to go on lives in :class:`HalfBuffers` (``save``/``load``), so a later run
with a larger time budget continues from the passes already rendered.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from dermis.geometry.regions import REGION_LABELS, REGIONS
from dermis.groundtruth.noise import two_seed_noise
from dermis.rendering.color import LUMINANCE

__all__ = ["PassSettings", "HalfBuffers", "Tile", "TILE_PIXELS", "TASK_PATHS", "tile_seed", "region_rel_se",
           "next_pass", "render_pass", "refine"]

# Pixels per task: a pass of the default scene (4,000 head pixels at 100^2) spreads over a
# few workers.
TILE_PIXELS = 1024
# Paths per half a task's samples are cut into: ~1-2 s of volpathmis on 2 cores (about 30 us
# a path, bench/results/reference_passes.json), so a call's fixed cost stays small while a
# long adaptive pass still spreads over many workers.
TASK_PATHS = 1 << 16


@dataclass(frozen=True)
class PassSettings:
    """When to stop and how big the passes are (``[reference]``, docs/ground-truth.md).

    pass_spp : the smallest number of samples per pixel and half a pass adds
    min_spp : every head pixel gets at least this many per half (block noise of the ranking)
    max_spp : no pixel gets more than this many per half
    target_rel_se : stop when every face region's luminance mean has at most this relative
        standard error
    budget_s : stop before a pass that would end after this many seconds of rendering (0: no
        time limit)
    max_passes : stop after this many passes (0: no limit)
    required_rel_se : every region reaches this relative standard error before the time budget
        may stop the passes (0: no guarantee, the budget stops them at any point); only
        ``max_paths``, ``max_passes`` and ``max_spp`` stop them short of it
    max_paths : stop before a pass that would take the paths traced (both halves) beyond
        this (0: no limit): the hard cap of the guaranteed part
    """

    pass_spp: int = 8
    min_spp: int = 32
    max_spp: int = 4096
    target_rel_se: float = 0.01
    budget_s: float = 0.0
    max_passes: int = 0
    required_rel_se: float = 0.0
    max_paths: int = 0

    def required_met(self, rel: dict) -> bool:
        """Whether regions of relative errors ``rel`` meet the guaranteed part (always, when
        there is no ``required_rel_se``)."""
        return not self.required_rel_se or (bool(rel) and
                                             max(rel.values()) <= self.required_rel_se)


@dataclass
class HalfBuffers:
    """Sums of the two half-buffers and what was spent on them.

    sum_a, sum_b : (H, W, 3) float64 sums of the samples of each half
    count : (H, W) int64 samples per pixel in each half (the halves always have the same)
    log : one dict per pass (pixels, spp, seconds, worst region's relative error after it)
    """

    sum_a: np.ndarray
    sum_b: np.ndarray
    count: np.ndarray
    log: list = field(default_factory=list)

    @classmethod
    def empty(cls, height: int, width: int) -> "HalfBuffers":
        return cls(np.zeros((height, width, 3)), np.zeros((height, width, 3)),
                   np.zeros((height, width), np.int64))

    @property
    def passes(self) -> int:
        return len(self.log)

    @property
    def seconds(self) -> float:
        return float(sum(p["seconds"] for p in self.log))

    @property
    def paths(self) -> int:
        """Paths traced into both halves."""
        return 2 * int(self.count.sum())

    def halves(self) -> tuple[np.ndarray, np.ndarray]:
        """The two half images (per-pixel means; 0 where a pixel has no sample)."""
        n = np.maximum(self.count, 1)[..., None]
        return self.sum_a / n, self.sum_b / n

    def image(self) -> np.ndarray:
        a, b = self.halves()
        return (a + b) / 2.0

    def half_diff(self) -> np.ndarray:
        a, b = self.halves()
        return (a - b) / 2.0

    def save(self, path: Path) -> None:
        np.savez(path, sum_a=self.sum_a, sum_b=self.sum_b, count=self.count,
                 log=np.array(json.dumps(self.log)))

    @classmethod
    def load(cls, path: Path) -> "HalfBuffers":
        with np.load(path) as z:
            return cls(z["sum_a"].copy(), z["sum_b"].copy(), z["count"].copy(),
                       json.loads(str(z["log"])))


@dataclass(frozen=True)
class Tile:
    """One task: ``spp`` samples per half at ``pixels`` ((M, 2) int32 x, y) with ``seeds``
    (half A, half B)."""

    pixels: np.ndarray
    spp: int
    seeds: tuple


def tile_seed(seed: int, pass_index: int, tile: int, half: int) -> int:
    """A 32-bit sampler seed of (seed, pass, tile, half) alone (independent streams)."""
    h = hashlib.sha256(f"dermis-reference:{seed}:{pass_index}:{tile}:{half}".encode())
    return int.from_bytes(h.digest()[:4], "little")


def region_rel_se(buffers: HalfBuffers, labels: np.ndarray) -> dict:
    """Per face region with pixels: the relative standard error of its luminance mean,
    sqrt(sum over its pixels of (luminance of (A - B) / 2)^2) / N / mean luminance."""
    a, b = buffers.halves()
    img, hd = (a + b) / 2.0 @ LUMINANCE, (a - b) / 2.0 @ LUMINANCE
    out = {}
    for name in REGIONS:
        sel = labels == REGION_LABELS[name]
        n = int(sel.sum())
        if n == 0:
            continue
        mean = float(img[sel].mean())
        se = math.sqrt(float((hd[sel] ** 2).sum())) / n
        out[name] = se / mean if mean > 0 else (0.0 if se == 0 else math.inf)
    return out


def next_pass(buffers: HalfBuffers, hit: np.ndarray, labels: np.ndarray,
              settings: PassSettings, target: float | None = None
              ) -> tuple[np.ndarray, np.ndarray, str | None]:
    """The next pass toward ``target`` (None: ``settings.target_rel_se``): (H, W) int64
    samples per half to add at each pixel, the regions' relative errors, and why to stop
    instead (``"target"``, ``"max_spp"``; None: go on)."""
    target = settings.target_rel_se if target is None else target
    add = np.zeros(hit.shape, np.int64)
    rel = region_rel_se(buffers, labels) if buffers.count.any() else {}
    low = hit & (buffers.count < settings.min_spp)
    if low.any():
        add[low] = np.minimum(settings.min_spp - buffers.count[low],
                              max(settings.pass_spp, int(buffers.count[low].min()) or 0))
        add[low] = np.maximum(add[low], 1)
        return add, rel, None
    # the worst regions first (those within 2x of the worst): under a time budget the small,
    # dark ones (nostril, ear) get the samples before the large ones go below the target
    # (default scene, 40 s: the nostril stayed at 4-6 % while the forehead reached 1.6 %)
    worst = max(rel.values(), default=0.0)
    wanting = [r for r, s in rel.items() if s > max(target, worst / 2)]
    if not wanting:
        return add, rel, "target"
    for name in wanting:
        sel = hit & (labels == REGION_LABELS[name]) & (buffers.count < settings.max_spp)
        if not sel.any():
            continue
        n = int(buffers.count[sel].min())
        need = math.ceil(n * (rel[name] / target) ** 2) - n
        step = min(max(need, settings.pass_spp), max(n, settings.pass_spp))
        add[sel] = np.minimum(step, settings.max_spp - buffers.count[sel])
    if not add.any():
        return add, rel, "max_spp"
    return add, rel, None


def _tiles(add: np.ndarray, seed: int, pass_index: int) -> list[Tile]:
    """The pass's tasks: pixels grouped by samples to add, in flat-index order, cut into
    tiles of :data:`TILE_PIXELS`, whose samples are cut into chunks of about
    :data:`TASK_PATHS` paths per half."""
    tiles = []
    for spp in np.unique(add[add > 0]):
        ys, xs = np.nonzero(add == spp)
        pix = np.stack([xs, ys], axis=1).astype(np.int32)
        for lo in range(0, len(pix), TILE_PIXELS):
            part = pix[lo:lo + TILE_PIXELS]
            chunk = max(1, TASK_PATHS // len(part))
            for done in range(0, int(spp), chunk):
                t = len(tiles)
                tiles.append(Tile(part, min(chunk, int(spp) - done),
                                  (tile_seed(seed, pass_index, t, 0),
                                   tile_seed(seed, pass_index, t, 1))))
    return tiles


def render_pass(trace_tiles: Callable[[list], list], buffers: HalfBuffers, add: np.ndarray, *,
                seed: int) -> float:
    """Trace one pass into ``buffers``: ``trace_tiles(tiles)`` returns each tile's (sums of
    half A, sums of half B[, seconds it took]), in any way (serially, on workers); they are
    added in tile order.  Returns its seconds, the tasks' own seconds and this process's CPU
    seconds (its Mitsuba threads' included)."""
    t0, c0 = time.perf_counter(), time.process_time()
    tiles = _tiles(add, seed, buffers.passes)
    task_seconds = []
    for tile, (a, b, *took) in zip(tiles, trace_tiles(tiles)):
        task_seconds += took
        x, y = tile.pixels[:, 0], tile.pixels[:, 1]
        buffers.sum_a[y, x] += a
        buffers.sum_b[y, x] += b
        buffers.count[y, x] += tile.spp
    return time.perf_counter() - t0, task_seconds, time.process_time() - c0


def refine(trace_tiles: Callable[[list], list], buffers: HalfBuffers, hit: np.ndarray,
           labels: np.ndarray, settings: PassSettings, *, seed: int,
           progress: Callable[[float], None] | None = None) -> str:
    """Add passes to ``buffers``: first toward ``required_rel_se`` whatever the time, then
    toward ``target_rel_se`` within the time budget (:class:`PassSettings`), until
    :func:`next_pass` says stop or a limit is reached.  Returns why it stopped: ``"target"``,
    ``"max_spp"``, ``"budget"``, ``"max_paths"`` or ``"max_passes"``."""
    while True:
        rel = region_rel_se(buffers, labels) if buffers.count.any() else {}
        guaranteed = not settings.required_met(rel) or not buffers.count[hit].all()
        aim = settings.required_rel_se if guaranteed and settings.required_rel_se \
            else settings.target_rel_se
        add, rel, stop = next_pass(buffers, hit, labels, settings, target=aim)
        if stop == "target" and aim != settings.target_rel_se:   # required met: refine
            guaranteed = False
            add, rel, stop = next_pass(buffers, hit, labels, settings)
        if stop:
            return stop
        if settings.max_passes and buffers.passes >= settings.max_passes:
            return "max_passes"
        if settings.max_paths and buffers.paths + 2 * int(add.sum()) > settings.max_paths:
            return "max_paths"
        if settings.budget_s > 0 and buffers.passes and not (guaranteed and
                                                             settings.required_rel_se):
            # the next pass's time, from the seconds per path so far
            per_path = buffers.seconds / max(buffers.paths, 1)
            if buffers.seconds + per_path * 2 * int(add.sum()) > settings.budget_s:
                return "budget"
        uniform = bool(add[hit].all())
        seconds, task_seconds, cpu_seconds = render_pass(trace_tiles, buffers, add, seed=seed)
        rel = region_rel_se(buffers, labels)
        entry = {"pixels": int((add > 0).sum()), "paths": 2 * int(add.sum()),
                 "seconds": seconds, "cpu_seconds": cpu_seconds,
                 "worst_rel_se": max(rel.values()) if rel else 0.0,
                 "uniform": uniform, "guaranteed": bool(guaranteed and settings.required_rel_se),
                 "spp_min": 2 * int(buffers.count[hit].min()), "task_seconds": task_seconds}
        if uniform:   # the noise-vs-samples curve of the whole head (reports/ground_truth.py)
            a, b = buffers.halves()
            entry["noise"] = {f: v["rel"] for f, v in two_seed_noise(a, b, hit).items()}
        buffers.log.append(entry)
        if progress is not None:
            worst = max(rel.values()) if rel else 0.0
            frac = min(1.0, (settings.target_rel_se / worst) ** 2) if worst > 0 else 1.0
            if settings.budget_s > 0 and settings.required_met(rel):
                frac = max(frac, min(1.0, buffers.seconds / settings.budget_s))
            progress(frac)
