"""The report's opening pages: every model's distance to the path-traced reference with error bars of
both images' noise (reports/truth_noise.py, reports/ground_truth.py, reports/truth_pages.py,
reports/truth_verdicts.py, stages/report.py).

Synthetic RenderedImages only, no Mitsuba, built so that every standard error has a closed
form.  Reference pixels come in 8 x 8 tiles, each of one face region (or none) whose colour
c is uniform; e = +-1 alternates between 4 x 4 blocks, so every tile holds as many + as -
pixels.  The reference's half buffers are T (1 + 2 s e) and T: its image T (1 + s e) carries
the realised noise s T e, which its half-difference (A - B) / 2 = s T e estimates exactly.
Hence a region of n pixels has mean c and standard error s c / sqrt(n) per channel
(relative: s / sqrt(n)); the 4 x 4 block means' relative noise is s / sqrt(1 + s^2).  A model
is f T (1 + s_m e') at twice the resolution, e' = +-1 in stripes of 4 x 4 blocks (balanced in
each tile and orthogonal to e), with its half-difference f s_m T e' or no noise field at
all.  Then, summing over tiles, the relative RMSE on 4 x 4 blocks is
e^2 = ((f - 1)^2 + f^2 s_m^2 + s^2) / (1 + s^2), and noise alone gives
(s^2 + f^2 s_m^2) / (1 + s^2) of it.
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess
from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pytest

from dermis.geometry.regions import REGION_LABELS, REGIONS, region_stats
from dermis.groundtruth.noise import two_seed_noise
from dermis.pipeline.artifacts import RenderedImage, load, save
from dermis.rendering.color import LUMINANCE
from dermis.reports import truth_noise
from dermis.reports.ground_truth import ground_truth_metrics, metrics_ground_truth
from dermis.reports.truth_noise import FAILS, HOLDS, UNRESOLVED, VERDICTS
from dermis.reports.truth_verdicts import decide

H = W = 32          # reference pixels
F = 2               # camera pixels per reference pixel (each way)
TILE = 8            # region tiles
LIGHT = "point"
# float64 sums of float32 images: 1e-6 relative is far below every quantity tested
EXACT = 1e-6
NLAB = len(REGIONS) + 1     # labels 0 (none) .. len(REGIONS)
COLOURS = np.random.default_rng(3).uniform(0.2, 1.0, (NLAB, 3))   # per label


def _layout():
    """(labels (H, W), T (H, W, 3), e (H, W), e' (H, W)): 16 tiles, tile k -> label k mod
    NLAB (every region has at least two tiles)."""
    labels = np.zeros((H, W), np.int8)
    for k in range(16):
        i, j = divmod(k, 4)
        labels[i * TILE:(i + 1) * TILE, j * TILE:(j + 1) * TILE] = k % NLAB
    y, x = np.mgrid[0:H, 0:W]
    e = np.where(((y // 4) + (x // 4)) % 2 == 0, 1.0, -1.0)
    e2 = np.where((y // 4) % 2 == 0, 1.0, -1.0)
    return labels, COLOURS[labels], e, e2


def _reference(s: float, *, with_noise: bool, rel_se: bool = True,
               extra_info: dict | None = None):
    """The reference as the reference stage returns it: image, mask, regions (with the
    standard errors of their means), block noise; ``rel_se``: the rewritten stage's
    ``region_rel_se``; ``with_noise``: the half-difference as the artifact's ``noise``."""
    labels, T, e, _ = _layout()
    a, b = T * (1 + 2 * s * e[..., None]), T
    mean, hd = (a + b) / 2, (a - b) / 2
    mask = np.ones((H, W), bool)
    info = {"model": "reference", "light": LIGHT, "geometry": "high", "spp": 64,
            "width": W, "height": H, "noise": two_seed_noise(a, b, mask),
            "regions": region_stats(mean, labels, half_diff=hd), **(extra_info or {})}
    if rel_se:
        info["region_rel_se"] = {r: _region_rel_se(r, s) for r in REGIONS}
    return RenderedImage(mean.astype(np.float32), mask, {"render": 12.0}, info,
                         noise=hd.astype(np.float32) if with_noise else None)


def _model(name: str, factor: float, s_model: float | None = None, seconds: float = 1.0):
    """f T (1 + s_m e') at camera resolution with its half-difference f s_m T e' (or f T
    and no noise field)."""
    _, T, _, e2 = _layout()
    up = lambda x: np.kron(x, np.ones((F, F, 1)))
    hd = factor * (s_model or 0.0) * T * e2[..., None]
    return RenderedImage(up(T * factor + hd).astype(np.float32),
                         np.ones((H * F, W * F), bool), {"total": seconds},
                         {"model": name, "light": LIGHT, "geometry": "high"},
                         noise=None if s_model is None else up(hd).astype(np.float32))


def _metrics(models: dict, ref):
    labels = _layout()[0]
    return ground_truth_metrics({f"render-{m}": im for m, im in models.items()}, {LIGHT: ref},
                                mesh=None, camera=None, region_labels={(H, W): labels})


def _region_n(name: str) -> int:
    return int((_layout()[0] == REGION_LABELS[name]).sum())


def _region_rel_se(name: str, s: float) -> float:
    """Closed form: the relative standard error of a region's luminance mean."""
    return s / math.sqrt(_region_n(name))


def _region_rel_se_channels_independent(name: str, s: float) -> float:
    """What a reference without ``region_rel_se`` gives: per-channel standard errors
    combined as if the channels were independent (sqrt(sum (s c_k L_k)^2) / (c . L))."""
    c = COLOURS[REGION_LABELS[name]]
    return s * math.sqrt(float(((c * LUMINANCE) ** 2).sum())) / float(c @ LUMINANCE) \
        / math.sqrt(_region_n(name))


# the region with the fewest pixels: its reference standard error is set to 0.5 %
SMALL = min(REGIONS, key=_region_n)
S_REF = 0.005 * math.sqrt(_region_n(SMALL))


def _block_e2(f: float, s: float, s_m: float = 0.0) -> float:
    return ((f - 1) ** 2 + f * f * s_m * s_m + s * s) / (1 + s * s)


# ------------------------------------------------------------------------------ error bars
@pytest.mark.parametrize("ref_noise_field", [False, True])
def test_region_error_bar_is_the_quadrature_sum_of_both_noises(ref_noise_field):
    """A model 5 % bright with its own noise s_m: sigma_r^2 = (f s_m / sqrt n)^2 +
    f^2 (s / sqrt n)^2 per region (f = 1.05), whether the reference's noise comes from its
    region records or from its half-difference; without the model's noise only the
    reference's term."""
    ref = _reference(S_REF, with_noise=ref_noise_field)
    s_m, f = 0.03, 1.05
    gt = _metrics({"lafortune": _model("lafortune", f, s_m), "hk93": _model("hk93", f)}, ref)
    for name in REGIONS:
        n = _region_n(name)
        with_own = gt["models"][f"lafortune-{LIGHT}"]["regions"][name]
        without = gt["models"][f"hk93-{LIGHT}"]["regions"][name]
        assert abs(with_own["rel_lum"] - 0.05) < EXACT and abs(without["rel_lum"] - 0.05) < EXACT
        want = math.sqrt((f * s_m / math.sqrt(n)) ** 2 + (f * S_REF / math.sqrt(n)) ** 2)
        assert with_own["sigma_lum"] == pytest.approx(want, rel=1e-5), name
        assert with_own["model_se_lum"] == pytest.approx(f * s_m / math.sqrt(n), rel=1e-5)
        assert without["sigma_lum"] == pytest.approx(f * S_REF / math.sqrt(n), rel=1e-5)
        assert without["model_se_lum"] is None
        for c in range(3):   # per channel the same (the noise is proportional to the colour)
            assert with_own["sigma_rgb"][c] == pytest.approx(want, rel=1e-5)


def test_five_percent_resolved_three_tenths_not_at_half_a_percent_noise():
    """Against a region whose mean has 0.5 % relative standard error: 5 % off is resolved,
    0.3 % off is not (2 standard errors = 1 %)."""
    ref = _reference(S_REF, with_noise=False)
    gt = _metrics({"lafortune": _model("lafortune", 1.05), "bssrdf": _model("bssrdf", 1.003)},
                  ref)
    assert _region_rel_se(SMALL, S_REF) == pytest.approx(0.005)
    bright = gt["models"][f"lafortune-{LIGHT}"]["regions"][SMALL]
    close = gt["models"][f"bssrdf-{LIGHT}"]["regions"][SMALL]
    assert bright["sigma_lum"] == pytest.approx(1.05 * 0.005, rel=1e-5)
    assert close["sigma_lum"] == pytest.approx(1.003 * 0.005, rel=1e-5)
    assert bright["resolved"] and not close["resolved"]
    assert abs(close["rel_lum"] - 0.003) < EXACT


def test_distance_error_bar_combines_the_block_noises():
    """At the ranking scale (4 x 4 blocks): e^2, the reference's noise s / sqrt(1 + s^2),
    the model's own f s_m / sqrt(1 + s^2), stderr their quadrature sum, and the distance with
    the noise removed |f - 1| / sqrt(1 + s^2) (module docstring)."""
    ref = _reference(S_REF, with_noise=False)
    s_m, f = 0.02, 1.30
    gt = _metrics({"lafortune": _model("lafortune", f, s_m), "hk93": _model("hk93", 1.05)},
                  ref)
    k = math.sqrt(1 + S_REF ** 2)
    sc = gt["models"][f"lafortune-{LIGHT}"]["scales"]["4"]
    assert sc["rel_rmse"] == pytest.approx(math.sqrt(_block_e2(f, S_REF, s_m)), rel=1e-6)
    assert sc["ref_noise"] == pytest.approx(S_REF / k, rel=1e-6)
    assert sc["model_noise"] == pytest.approx(f * s_m / k, rel=1e-6)
    assert sc["noise"] == pytest.approx(math.hypot(S_REF, f * s_m) / k, rel=1e-6)
    assert sc["rel_rmse_true"] == pytest.approx(0.30 / k, rel=1e-6)
    assert sc["resolved"]                      # 0.30 > 2 x 0.068
    five = gt["models"][f"hk93-{LIGHT}"]["scales"]["4"]
    assert five["model_noise"] is None and five["noise"] == pytest.approx(S_REF / k, rel=1e-6)
    assert five["rel_rmse"] == pytest.approx(math.sqrt(_block_e2(1.05, S_REF)), rel=1e-6)
    assert not five["resolved"]                # 0.076 < 2 x 0.056: within the blocks' noise


def test_ranking_resolves_what_the_noise_allows():
    """0.3 % off is resolved closer than 5 % off (their difference is coherent over every
    block); 5 % bright and 4.9 % dark are tied (the reference's noise enters both equally
    but their differences from it are not coherent); the rank ranges follow."""
    ref = _reference(S_REF, with_noise=False)
    gt = _metrics({"bssrdf": _model("bssrdf", 1.003), "lafortune": _model("lafortune", 1.05),
                   "asperity": _model("asperity", 0.951), "hk93": _model("hk93", 0.7)}, ref)
    order = gt["ranking"][LIGHT]
    assert [r["model"] for r in order] == ["bssrdf", "asperity", "lafortune", "hk93"]
    assert [r["tied_with_previous"] for r in order] == [False, False, True, False]
    ranges = {r["model"]: (r["rank_best"], r["rank_worst"]) for r in order}
    assert ranges == {"bssrdf": (1, 1), "asperity": (2, 3), "lafortune": (2, 3), "hk93": (4, 4)}
    best = next(c for c in gt["thesis"] if c["model"] == "bssrdf")
    assert best["verdict"] == HOLDS
    # the BSSRDF 5.05 % dark against Lafortune 5 % bright: tied, the claim is not resolved
    gt = _metrics({"bssrdf": _model("bssrdf", 0.9495), "lafortune": _model("lafortune", 1.05),
                   "hk93": _model("hk93", 0.7)}, ref)
    best = next(c for c in gt["thesis"] if c["model"] == "bssrdf")
    assert best["values"][LIGHT] == {"rank": 2, "rank_best": 1, "rank_worst": 2}
    assert best["verdict"] == UNRESOLVED and best["per_light"][LIGHT] == UNRESOLVED
    # and 15 % bright against 5 %: resolved behind, the claim does not hold
    gt = _metrics({"bssrdf": _model("bssrdf", 1.15), "lafortune": _model("lafortune", 1.05)},
                  ref)
    assert next(c for c in gt["thesis"] if c["model"] == "bssrdf")["verdict"] == FAILS


def test_contrast_standard_error_matches_monte_carlo():
    """The noise-removed contrast and its standard error against 4000 noisy draws."""
    from dermis.reports.ground_truth import _contrast
    rng = np.random.default_rng(11)
    x0 = rng.uniform(0.2, 1.0, 200)
    v = (0.05 * x0) ** 2
    got = [_contrast(x0 + rng.standard_normal(x0.size) * np.sqrt(v), v) for _ in range(4000)]
    c, se = np.array([g[0] for g in got]), np.array([g[1] for g in got])
    true = x0.std() / x0.mean()
    # spread of 4000 draws known to ~1.1 %; the first-order formula within 10 %
    assert np.std(c) == pytest.approx(np.mean(se), rel=0.10)
    assert abs(c.mean() - true) < 4 * np.std(c) / math.sqrt(4000) + 0.002 * true


def test_pair_test_standard_error_matches_monte_carlo():
    """pair_test's standard error of s_a - s_b against the spread over 4000 noise draws."""
    rng = np.random.default_rng(7)
    K = 300
    M0 = rng.uniform(0.5, 1.0, (K, 3))
    Ta, Tb = M0 * 1.05, M0 * 0.97
    vM, va, vb = (0.03 * M0) ** 2, (0.02 * M0) ** 2, np.zeros((K, 3))
    diffs, ses = [], []
    for _ in range(4000):
        M = M0 + rng.standard_normal(M0.shape) * np.sqrt(vM)
        Da = Ta + rng.standard_normal(M0.shape) * np.sqrt(va)
        d, se, _ = truth_noise.pair_test(Da, va, Tb, vb, M, vM)
        diffs.append(d)
        ses.append(se)
    # the spread of 4000 draws is known to ~1.1 % (1 / sqrt(2 x 4000)); the formula is first
    # order, with the noisy-image estimates of u^2 (slightly conservative): within 10 %
    assert np.std(diffs) == pytest.approx(np.mean(ses), rel=0.10)
    true = float((((Ta - M0) ** 2).sum() - ((Tb - M0) ** 2).sum()) / (M0 ** 2).sum())
    assert abs(np.mean(diffs) - true) < 4 * np.std(diffs) / math.sqrt(4000)   # unbiased


# ------------------------------------------------------------------------------ verdicts
def test_verdicts_are_exactly_three_and_follow_the_error_bars():
    assert VERDICTS == ("holds", "does not hold", "not resolved at this noise")
    assert decide([(0.05, 0.005)]) == HOLDS
    assert decide([(-0.05, 0.005)]) == FAILS
    assert decide([(0.003, 0.005)]) == UNRESOLVED         # within 2 standard errors
    assert decide([(0.05, 0.005), (0.003, 0.005)]) == UNRESOLVED
    assert decide([(0.05, 0.005), (-0.05, 0.005)]) == FAILS
    # HK93 a uniform 0.7 x T: its contrast equals the reference's (noise removed, here from
    # its half-difference, exactly), so "soft" (< 0.95 x the reference's) does not hold
    ref = _reference(S_REF, with_noise=True)
    gt = _metrics({m: _model(m, f) for m, f in (("bssrdf", 1.0), ("lafortune", 1.05),
                                                ("asperity", 0.9), ("hk93", 0.7))}, ref)
    assert {c["verdict"] for c in gt["thesis"]} <= set(VERDICTS)
    for c in gt["thesis"]:
        assert set(c["per_light"].values()) <= set(VERDICTS)
    soft = next(c for c in gt["thesis"] if c["model"] == "hk93")
    v = soft["values"][LIGHT]
    assert v["hk93"] == pytest.approx(v["reference"], rel=1e-6)
    # at this noise the 5 % margin is within 2 standard errors: not resolved
    assert 0 < 0.05 * v["hk93"] < 2 * v["reference_stderr"]
    assert soft["verdict"] == UNRESOLVED
    # at a fifth of it, resolved: does not hold
    ref = _reference(S_REF / 5, with_noise=True)
    gt = _metrics({"bssrdf": _model("bssrdf", 1.0), "hk93": _model("hk93", 0.7)}, ref)
    soft = next(c for c in gt["thesis"] if c["model"] == "hk93")
    v = soft["values"][LIGHT]
    assert 0.05 * v["hk93"] > 2 * v["reference_stderr"] > 0
    assert soft["verdict"] == FAILS
    # with the model 10 % flatter than the reference (its contrast scaled, mean kept) it holds
    labels, T, _, _ = _layout()
    lum = T @ LUMINANCE
    flat = T * ((lum.mean() + 0.8 * (lum - lum.mean())) / lum)[..., None] * 0.7
    hk = RenderedImage(np.kron(flat, np.ones((F, F, 1))).astype(np.float32),
                       np.ones((H * F, W * F), bool), {"total": 1.0},
                       {"model": "hk93", "light": LIGHT, "geometry": "high"})
    gt = _metrics({"bssrdf": _model("bssrdf", 1.0), "hk93": hk}, ref)
    assert next(c for c in gt["thesis"] if c["model"] == "hk93")["verdict"] == HOLDS


# ------------------------------------------------------------------------------ metrics.json
def test_metrics_json_ground_truth_keys_and_values():
    """``ground_truth.<light>``: the reference's region means and relative standard errors,
    every model's distance, stderr and resolution, its regions, and the noise reached, for
    today's references (no passes, no ``region_rel_se``) and the rewritten stage's."""
    passes = {"passes": 6, "stopped": "target", "target_rel_se": 0.01, "budget_s": 600.0}
    s_m, f = 0.01, 1.05
    k = math.sqrt(1 + S_REF ** 2)
    for extra, rel_se in (({}, False), (passes, True)):
        ref = _reference(S_REF, with_noise=False, rel_se=rel_se, extra_info=extra)
        gt = _metrics({"lafortune": _model("lafortune", f, s_m),
                       "bssrdf": _model("bssrdf", 1.003)}, ref)
        obj = json.loads(json.dumps(metrics_ground_truth(gt)))   # JSON-able
        g = obj[LIGHT]
        se = _region_rel_se if rel_se else _region_rel_se_channels_independent
        for name in REGIONS:
            r = g["regions"][name]
            assert r["ref_mean_rgb"] == pytest.approx(COLOURS[REGION_LABELS[name]], rel=1e-6)
            assert r["ref_rel_se"] == pytest.approx(se(name, S_REF), rel=1e-6)
            assert r["ref_rel_se_rgb"] == pytest.approx([_region_rel_se(name, S_REF)] * 3,
                                                        rel=1e-6)
        m = g["models"]["lafortune"]
        assert m["distance"] == pytest.approx(math.sqrt(_block_e2(f, S_REF, s_m)), rel=1e-6)
        assert m["stderr"] == pytest.approx(math.hypot(S_REF, f * s_m) / k, rel=1e-6)
        assert m["resolved"] is False and m["own_noise"] is True and m["scale"] == 4
        assert m["regions"][SMALL]["rel_diff"] == pytest.approx(0.05, abs=EXACT)
        assert m["regions"][SMALL]["resolved"] is True
        assert g["models"]["bssrdf"]["regions"][SMALL]["resolved"] is False
        assert g["models"]["bssrdf"]["own_noise"] is False
        assert g["models"]["bssrdf"]["rank_range"] == [1, 1]
        assert g["ranking"] == ["bssrdf", "lafortune"]
        nr = g["noise_reached"]
        assert nr["spp"] == 64
        worst = max(se(r, S_REF) for r in REGIONS)
        assert se(nr["worst_region"], S_REF) == pytest.approx(worst, rel=1e-9)
        assert nr["worst_region_rel_se"] == pytest.approx(worst, rel=1e-6)
        for key in ("passes", "stopped", "target_rel_se", "budget_s"):
            assert nr[key] == extra.get(key)                  # None when not recorded


def test_the_page_says_which_noise_the_reference_reached():
    """Passes, stopping rule and target when the reference records them; a fixed sample
    count said as such when it does not (today's references)."""
    from dermis.reports.truth_pages import noise_reached_text
    base = {"width": 40, "height": 40, "spp": 64, "seconds": 12.0,
            "regions": {"nose": {"mean_rgb": [1.0, 1.0, 1.0], "stderr_rgb": [0.01] * 3}}}
    text = noise_reached_text(base)
    assert "fixed sample count" in text and "Worst region: nose" in text
    for stopped, words in (("target", "stopped at its target (region means to 1.0 %"),
                           ("budget", "stopped by its time budget (600 s) before its target"),
                           ("max_passes", "stopped at its maximum of passes before")):
        text = noise_reached_text(dict(base, passes=6, stopped=stopped, target_rel_se=0.01,
                                       budget_s=600.0, region_rel_se={"nose": 0.008}))
        assert "6 passes" in text and words in text, text
        assert "nose, 0.8 %" in text


def test_rendered_image_noise_field_saves_and_loads(tmp_path):
    """The optional field: default None, saved with the arrays, read back (and an artifact
    saved before the field existed loads with None)."""
    im = _model("lafortune", 1.0, 0.01)
    save(im, tmp_path / "a")
    back = load(tmp_path / "a")
    assert np.array_equal(back.noise, im.noise)
    plain = _model("lafortune", 1.0)
    save(plain, tmp_path / "b")
    assert load(tmp_path / "b").noise is None
    fields = json.loads((tmp_path / "b" / "fields.json").read_text())
    fields.pop("noise")
    (tmp_path / "b" / "fields.json").write_text(json.dumps(fields))
    assert load(tmp_path / "b").noise is None


# ------------------------------------------------------------------------------ the report
def _run_report(tmp_path, monkeypatch, *, with_reference: bool):
    """The report stage on synthetic renders (labels of the synthetic layout)."""
    from dermis.pipeline.config import CameraConfig
    from dermis.reports import ground_truth
    from dermis.stages import report
    labels = _layout()[0]
    monkeypatch.setattr(ground_truth, "region_labels_for", lambda *a, **k: labels)
    models = {m: _model(m, f, 0.01 if m == "lafortune" else None)
              for m, f in (("bssrdf", 1.003), ("lafortune", 1.05), ("hk93", 0.7))}
    inputs = {f"render-{m}": im for m, im in models.items()}
    refs = []
    if with_reference:
        inputs["reference-point"] = _reference(S_REF, with_noise=False)
        inputs[report.GROUND_TRUTH_MESH] = None
        refs = ["reference-point"]
    params = {"renders": sorted(f"render-{m}" for m in models), "irradiance": {},
              "differences": [], "images": None, "references": refs,
              "reference_skipped": None if with_reference else
              "Reference stage skipped: Mitsuba 3 is not installed",
              "profiles": [], "scene_name": "synthetic", "credits": [],
              "camera": asdict(CameraConfig(width=W * F, height=H * F))}
    out = tmp_path / ("with" if with_reference else "without")
    ctx = SimpleNamespace(out_dir=out, cl=SimpleNamespace(description="test device"))
    out.mkdir()
    result = report.run(params, inputs, ctx)
    return out, result


def _page_text(pdf, page: int) -> str:
    return subprocess.run(["pdftotext", "-f", str(page), "-l", str(page), str(pdf), "-"],
                          capture_output=True, text=True, check=True).stdout


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="pdftotext (poppler) missing")
def test_report_leads_with_the_ground_truth(tmp_path, monkeypatch):
    """Page 1 (title) names the verdicts, page 2 is the ground-truth page; metrics.json has
    ``ground_truth`` and ``thesis``.  Without a reference the title page says why and
    ``ground_truth`` is empty."""
    out, result = _run_report(tmp_path, monkeypatch, with_reference=True)
    metrics = json.loads((out / "metrics.json").read_text())
    g = metrics["ground_truth"][LIGHT]
    assert g["models"]["lafortune"]["distance"] == pytest.approx(
        math.sqrt(_block_e2(1.05, S_REF, 0.01)), rel=1e-6)
    assert g["models"]["lafortune"]["own_noise"] and not g["models"]["hk93"]["own_noise"]
    assert metrics["model_vs_reference"]          # the BSSRDF differences are still there
    assert {c["verdict"] for c in metrics["thesis"]} <= set(VERDICTS)
    title, lead = _page_text(out / "report.pdf", 1), _page_text(out / "report.pdf", 2)
    assert "Summary: distance to ground truth" in title
    for c in metrics["thesis"]:
        assert c["verdict"] in title
    assert lead.startswith("Distance to ground truth, point")
    assert "own noise not estimated" in lead.lower() and "Reference noise reached" in lead
    d = {m: 100 * math.sqrt(_block_e2(f, S_REF, s_m)) for m, f, s_m in
         (("bssrdf", 1.003, 0), ("lafortune", 1.05, 0.01), ("hk93", 0.7, 0))}
    assert (f"bssrdf {d['bssrdf']:.1f} < lafortune {d['lafortune']:.1f} < hk93 {d['hk93']:.1f}"
            in " ".join(lead.split()))
    assert result.info["pages"] == int(subprocess.run(
        ["pdfinfo", str(out / "report.pdf")], capture_output=True, text=True,
        check=True).stdout.split("Pages:")[1].split()[0])

    out, _ = _run_report(tmp_path, monkeypatch, with_reference=False)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ground_truth"] == {} and "Mitsuba 3 is not installed" in \
        metrics["ground_truth_skipped"]
    title = _page_text(out / "report.pdf", 1)
    assert "Mitsuba 3 is not installed" in " ".join(title.split())
    assert "Distance to ground truth" not in _page_text(out / "report.pdf", 2)
