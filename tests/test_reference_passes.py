"""The reference's progressive passes (groundtruth/progressive.py, groundtruth/pixel_tracing.py,
stages/reference.py): two half-buffers give an unbiased error estimate, samples go where the
regions are noisy, the passes stop at the target or the budget, a larger budget continues
from the cached passes, the bytes do not depend on the number of workers, and a model knob
never re-renders the reference.

The first tests trace a synthetic image with known pixel means and Gaussian sample noise (no
Mitsuba); the last ones run the stage on a small quick head and skip without Mitsuba.
"""
from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from dermis.geometry.regions import REGION_LABELS
from dermis.groundtruth import progressive
from dermis.groundtruth.progressive import HalfBuffers, PassSettings, refine, region_rel_se
from dermis.rendering.color import LUMINANCE

H = W = 20
RNG = np.random.default_rng(5)
MU = RNG.uniform(0.2, 1.0, (H, W, 3))                      # the pixels' true means
SIGMA = np.full((H, W), 1.0)                               # per-sample noise (grey)
LABELS = np.zeros((H, W), np.int64)
LABELS[:, :10] = REGION_LABELS["cheek"]
LABELS[:, 10:] = REGION_LABELS["nose"]
SIGMA[:, 10:] = 4.0                                        # the nose is 4x noisier
HIT = np.ones((H, W), bool)


def fake_trace(tiles, *, same_seed=False):
    """Each tile's sums of Gaussian samples around MU, seeded by the tile's seeds."""
    out = []
    for t in tiles:
        x, y = t.pixels[:, 0], t.pixels[:, 1]
        sums = []
        for s in ((t.seeds[0], t.seeds[0]) if same_seed else t.seeds):
            g = np.random.default_rng(s)
            noise = g.standard_normal((len(x), t.spp)).sum(axis=1)
            sums.append(MU[y, x] * t.spp + (SIGMA[y, x] * noise)[:, None])
        out.append(tuple(sums))
    return out


def test01_half_buffers_estimate_the_error_without_bias():
    """(A - B) / 2 has the variance of the image's error: over 200 independent references
    the mean of sum hd^2 equals the mean of sum (image - truth)^2 within its sampling error,
    and the region standard error the buffers report equals the spread of the region means.
    Halves traced with one seed (correlated) would report no error at all: checked too."""
    n, reps = 8, 200
    settings = PassSettings(pass_spp=n, min_spp=n, max_spp=n, target_rel_se=1e-6)
    hd2, err2, se, means = [], [], [], []
    for r in range(reps):
        b = HalfBuffers.empty(H, W)
        assert refine(fake_trace, b, HIT, LABELS, settings, seed=r) == "max_spp"
        hd2.append(float((b.half_diff() ** 2).sum()))
        err2.append(float(((b.image() - MU) ** 2).sum()))
        se.append(region_rel_se(b, LABELS)["cheek"])
        sel = LABELS == REGION_LABELS["cheek"]
        means.append(float((b.image()[sel] @ LUMINANCE).mean()))
    # each sum has H*W*3 terms of variance 2 (sigma^2 / 2n)^2 (chi-square, 1 dof): the
    # ratio of the two means has relative standard error sqrt(2 * 2 / (3 H W reps))
    ratio = np.mean(hd2) / np.mean(err2)
    tol = 4 * math.sqrt(4.0 / (3 * H * W * reps))
    assert abs(ratio - 1) < tol, (ratio, tol)
    # the region's reported standard error vs the spread over repetitions (relative error
    # of a standard deviation from `reps` samples: 1 / sqrt(2 reps))
    true_mean = float((MU[LABELS == REGION_LABELS["cheek"]] @ LUMINANCE).mean())
    spread = np.std(means, ddof=1) / true_mean
    assert abs(np.sqrt(np.mean(np.square(se))) / spread - 1) < 4 / math.sqrt(2 * reps)
    # correlated halves: the estimate collapses although the error does not
    b = HalfBuffers.empty(H, W)
    refine(lambda t: fake_trace(t, same_seed=True), b, HIT, LABELS, settings, seed=1)
    assert float((b.half_diff() ** 2).sum()) == 0.0 and float(((b.image() - MU) ** 2).sum()) > 0


def test02_adaptive_passes_reach_the_target_with_fewer_paths():
    """The passes stop when every region's mean is known to the target; the noisier region
    got more samples per pixel; and it cost fewer paths than uniform sampling to the same
    target would (the noisy region sets the uniform count)."""
    settings = PassSettings(pass_spp=4, min_spp=8, max_spp=1 << 16, target_rel_se=0.002)
    b = HalfBuffers.empty(H, W)
    assert refine(fake_trace, b, HIT, LABELS, settings, seed=3) == "target"
    rel = region_rel_se(b, LABELS)
    assert max(rel.values()) <= settings.target_rel_se
    nose, cheek = b.count[LABELS == REGION_LABELS["nose"]], b.count[LABELS == REGION_LABELS["cheek"]]
    assert nose.min() > 4 * cheek.max()                    # sigma 4x: ~16x the samples
    # uniform: every pixel at the nose's count
    assert b.count.sum() < 0.6 * nose.min() * b.count.size
    # the passes decide from the buffers alone: the same seed gives the same bytes
    b2 = HalfBuffers.empty(H, W)
    refine(fake_trace, b2, HIT, LABELS, settings, seed=3)
    assert np.array_equal(b.sum_a, b2.sum_a) and np.array_equal(b.count, b2.count)


def test03_budget_and_pass_limits_and_resuming(monkeypatch, tmp_path):
    """A time budget stops before a pass that would overrun it (a fake clock: every traced
    path takes 1 ms); passes saved and loaded continue exactly as one run would."""
    clock = [0.0]

    def slow_trace(tiles):
        clock[0] += 1e-3 * sum(2 * len(t.pixels) * t.spp for t in tiles)
        return fake_trace(tiles)

    monkeypatch.setattr(progressive.time, "perf_counter", lambda: clock[0])
    settings = PassSettings(pass_spp=4, min_spp=8, max_spp=1 << 16, target_rel_se=1e-4,
                            budget_s=20.0)
    b = HalfBuffers.empty(H, W)
    assert refine(slow_trace, b, HIT, LABELS, settings, seed=7) == "budget"
    assert b.seconds <= 20.0 and b.passes >= 2
    # the pass limit, then resumed from disk with a larger one: the same bytes as one run
    few = PassSettings(pass_spp=4, min_spp=8, max_spp=1 << 16, target_rel_se=1e-4,
                       max_passes=3)
    more = PassSettings(pass_spp=4, min_spp=8, max_spp=1 << 16, target_rel_se=1e-4,
                        max_passes=6)
    a = HalfBuffers.empty(H, W)
    assert refine(fake_trace, a, HIT, LABELS, few, seed=9) == "max_passes"
    a.save(tmp_path / "p.npz")
    a = HalfBuffers.load(tmp_path / "p.npz")
    assert a.passes == 3
    refine(fake_trace, a, HIT, LABELS, more, seed=9)
    one = HalfBuffers.empty(H, W)
    refine(fake_trace, one, HIT, LABELS, more, seed=9)
    assert one.passes == a.passes == 6
    assert np.array_equal(one.sum_a, a.sum_a) and np.array_equal(one.sum_b, a.sum_b)


def test03b_the_required_part_does_not_depend_on_the_clock(monkeypatch):
    """Every region reaches ``required_rel_se`` by the same passes and the same bytes whatever
    the clock says: a clock on which every path takes 1 s (a budget of 20 s is spent before
    the first pass ends) and one on which paths take no time give the same buffers up to
    the pass that met the requirement; only the refinement after it stops at the budget.
    A hard cap on paths is what stops the guaranteed part short."""
    clock = [0.0]

    def timed_trace(per_path):
        def trace(tiles):
            clock[0] += per_path * sum(2 * len(t.pixels) * t.spp for t in tiles)
            return fake_trace(tiles)
        return trace

    monkeypatch.setattr(progressive.time, "perf_counter", lambda: clock[0])
    settings = PassSettings(pass_spp=4, min_spp=8, max_spp=1 << 16, target_rel_se=0.002,
                            required_rel_se=0.006, budget_s=20.0)
    slow = HalfBuffers.empty(H, W)
    assert refine(timed_trace(1.0), slow, HIT, LABELS, settings, seed=11) == "budget"
    assert slow.seconds > settings.budget_s                  # the budget was spent long ago
    assert max(region_rel_se(slow, LABELS).values()) <= settings.required_rel_se
    assert all(p["guaranteed"] for p in slow.log)            # it stopped as soon as met
    fast = HalfBuffers.empty(H, W)
    assert refine(timed_trace(0.0), fast, HIT, LABELS, settings, seed=11) == "target"
    assert fast.passes > slow.passes
    upto = HalfBuffers.empty(H, W)
    refine(timed_trace(0.0), upto, HIT, LABELS,
           PassSettings(**{**settings.__dict__, "max_passes": slow.passes}), seed=11)
    assert np.array_equal(upto.sum_a, slow.sum_a) and np.array_equal(upto.sum_b, slow.sum_b)
    assert np.array_equal(upto.count, slow.count)
    # the hard cap: fewer paths than the requirement needs stop it, on any clock
    capped = PassSettings(**{**settings.__dict__, "max_paths": slow.paths // 2})
    c = HalfBuffers.empty(H, W)
    assert refine(timed_trace(1.0), c, HIT, LABELS, capped, seed=11) == "max_paths"
    assert c.paths <= capped.max_paths
    assert max(region_rel_se(c, LABELS).values()) > settings.required_rel_se


def test03c_one_scene_per_lighting_condition_whatever_the_camera():
    """A close-up traces the scene of its lighting condition through its own sensor: the
    loaded scene's key is the same for two cameras and two jobs, and differs for other lights,
    another mesh or another export; a job without a mesh key keeps a scene of its own."""
    from dataclasses import replace
    from dermis.groundtruth.pixel_tracing import TraceJob
    from dermis.groundtruth.scene_export import HeadSceneOptions
    from dermis.optics.layers import PRESETS
    from dermis.pipeline.config import CameraConfig, LightConfig
    point = LightConfig(name="point", type="point", position=(1.0, 2.0, 3.0))
    other = LightConfig(name="point", type="point", position=(1.0, 2.0, 4.0))
    cam = CameraConfig()
    near = replace(cam, fov_deg=cam.fov_deg / 4)
    job = TraceJob("a", None, PRESETS["two_layer"], cam, [point], 20, 20,
                   HeadSceneOptions(roughness=0.3, tint_rd=np.array([0.5, 0.4, 0.3])),
                   "llvm_ad_rgb", "mesh-key")
    assert replace(job, token="b", camera=near).scene_key == job.scene_key
    for changed in (replace(job, lights=[other]), replace(job, mesh_key="another"),
                    replace(job, options=replace(job.options, roughness=0.2))):
        assert changed.scene_key != job.scene_key
    assert replace(job, mesh_key="").scene_key == "a"


# ------------------------------------------------------------------------ with Mitsuba
def _mitsuba():
    from dermis.groundtruth import mitsuba
    why = mitsuba.mitsuba_missing_reason()
    if why:
        pytest.skip(why)
    return mitsuba.load_mitsuba("auto")


def _scene(tmp_path, **ref):
    from dermis.pipeline.api import load_scene
    from tests.scene_toml import QUICK
    over = {"camera": {"width": 40, "height": 40}, "mesh": {"high_triangles": 8000},
            "render": {"models": ["lafortune"], "lights": ["point"], "geometries": ["high"]},
            "output": {"previews": False, "output_dir": str(tmp_path / "out")},
            "reference": {"enabled": True, "width": 20, "height": 20, "min_spp": 4,
                          "pass_spp": 4, "target_rel_se": 0.001, "budget_s": 0,
                          "slab_samples": 4096, **ref}}
    return load_scene(QUICK, overrides=over)


def _reference_entry(summary):
    from pathlib import Path
    rep = next(n for n in summary.nodes if n.id == "reference-point")
    return rep, Path(rep.path)


def _digest(folder) -> str:
    h = hashlib.sha256()
    for name in ("reference-point.exr", "reference-point-halfA.exr", "reference-point-halfB.exr",
                 "reference-point-spp.exr"):   # passes.npz also logs each pass's seconds
        h.update((folder / name).read_bytes())
    return h.hexdigest()


def test04_trace_pixels_agrees_with_mitsubas_render(tmp_path):
    """Paths started only at the head's pixels give the image ``mi.render`` gives (its box
    filter): the head's mean agrees within 4 standard errors of the two estimates."""
    mi = _mitsuba()
    from dermis.groundtruth.passes import pixel_hits
    from dermis.groundtruth.pixel_tracing import trace_pixels
    from dermis.groundtruth.scene_export import HeadSceneOptions, head_scene, release
    from dermis.pipeline.api import run
    scene = _scene(tmp_path)
    summary = run(scene, cache=tmp_path / "c", until="mesh_high", export=False)
    from dermis.pipeline import artifacts
    mesh = artifacts.load(next(n for n in summary.nodes if n.id == "mesh_high").path)
    head = head_scene(mi, mesh, scene.optics, scene.camera, scene.light_groups()[0][1],
                      width=20, height=20, options=HeadSceneOptions(roughness=0.3))
    try:
        hit, _ = pixel_hits(mi, head.scene, width=20, height=20)
        ys, xs = np.nonzero(hit)
        px = np.stack([xs, ys], axis=1)
        mine = [trace_pixels(mi, head.scene, px, 64, s, width=20, height=20) / 64
                for s in range(4)]
        theirs = [np.asarray(mi.render(head.scene, spp=64, seed=100 + s), np.float64)
                  [..., :3][hit] for s in range(4)]
    finally:
        release(head)
    m = np.array([x.mean(axis=0) for x in mine])
    t = np.array([x.mean(axis=0) for x in theirs])
    se = np.sqrt(m.var(axis=0, ddof=1) / 4 + t.var(axis=0, ddof=1) / 4)
    assert np.all(np.abs(m.mean(axis=0) - t.mean(axis=0)) < 4 * se + 1e-12), (m, t, se)


def test05_resume_workers_and_model_knobs(tmp_path):
    """A run limited to 2 passes, then one allowed 4, continues from the cached 2 and
    writes the bytes of a fresh 4-pass run; 2 Dask workers write the same bytes as this
    process; changing a model's knob leaves the reference cached."""
    _mitsuba()
    from dermis.pipeline.api import run
    from dermis.pipeline.taskpool import task_pool
    run(_scene(tmp_path, max_passes=2), cache=tmp_path / "a", export=False)
    rep, entry = _reference_entry(run(_scene(tmp_path, max_passes=4), cache=tmp_path / "a",
                                      export=False))
    import json
    info = json.loads((entry / "meta.json").read_text())["info"]
    assert rep.status == "ran" and info["resumed_passes"] == 2 and info["passes"] == 4
    _, fresh = _reference_entry(run(_scene(tmp_path, max_passes=4), cache=tmp_path / "b",
                                    export=False))
    assert _digest(entry) == _digest(fresh)
    with task_pool(workers=2) as pool:
        _, dask = _reference_entry(run(_scene(tmp_path, max_passes=4), cache=tmp_path / "d",
                                       export=False, tasks=pool))
    assert _digest(dask) == _digest(fresh)
    # a model knob: the render node reruns, the reference does not
    knob = _scene(tmp_path, max_passes=4)
    from dataclasses import replace
    knob = replace(knob, render=replace(knob.render, spp=2))
    summary = run(knob, cache=tmp_path / "b", export=False)
    status = {n.id: n.status for n in summary.nodes}
    assert status["reference-point"] == "cached" and status["render-lafortune-point-high"] == "ran"
