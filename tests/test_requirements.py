"""What a scene requires (reports/requirements.py): effects are visible or absent by their
size against the threshold and both images' noise; the cheapest model is one whose error is
within the accuracy by two standard errors, never one that misses it or is unresolved."""
from __future__ import annotations

import numpy as np
import pytest

from dermis.geometry.regions import REGION_LABELS
from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.errors import ConfigError
from dermis.reports.requirements import scene_requirements

H = W = 40
LABELS = np.zeros((H, W), np.int8)
LABELS[:, :20] = REGION_LABELS["cheek"]
LABELS[:, 20:] = REGION_LABELS["ear"]


def image(model, value, *, light="point", geometry="high", seconds=1.0, noise=None):
    lin = np.broadcast_to(np.asarray(value, np.float32), (H, W, 3)).copy() \
        if np.ndim(value) <= 1 else np.asarray(value, np.float32)
    return RenderedImage(lin, np.ones((H, W), bool), {"total": seconds},
                         {"model": model, "light": light, "geometry": geometry}, noise=noise)


def ear_brighter(base, rel):
    """An image of ``base`` whose ear half is ``rel`` brighter."""
    out = np.full((H, W, 3), base, np.float32)
    out[:, 20:] *= 1.0 + rel
    return out


def run(images, **kw):
    return scene_requirements({f"i{k}": im for k, im in enumerate(images)}, lambda l: LABELS,
                              accuracy=kw.pop("accuracy", 0.02),
                              threshold=kw.pop("threshold", 0.01), **kw)


def test01_an_effect_is_visible_where_its_pair_differs_and_absent_elsewhere():
    req = run([image("bssrdf", 0.5), image("bssrdf_mc", ear_brighter(0.5, 0.05))])
    rows = req["main"]["point"]["regions"]
    ear, cheek = rows["ear"]["effects"]["profile shape"], rows["cheek"]["effects"]["profile shape"]
    assert ear["verdict"] == "visible" and abs(ear["signed"] - 0.05) < 1e-6
    assert cheek["verdict"] == "absent" and abs(cheek["signed"]) < 1e-6
    # a pair the run did not render is listed with what it needs
    assert rows["ear"]["effects"]["mesh detail"] == {"measured": False,
                                                     "needs": ["bssrdf on low_bump"]}


def test02_noise_makes_a_small_effect_unresolved_not_visible():
    rng = np.random.default_rng(1)
    # per-pixel noise 0.5 of the mean: the region mean's s.e. is 0.5 / sqrt(800) ~ 1.8 %
    hd = (rng.standard_normal((H, W, 3)) * 0.25).astype(np.float32)
    a = image("asperity", ear_brighter(0.5, 0.02), noise=hd)
    b = image("lambert", 0.5)
    e = run([a, b])["main"]["point"]["regions"]["ear"]["effects"]["asperity"]
    assert e["stderr"] > 0.005 and e["verdict"] == "unresolved"
    e = run([image("asperity", ear_brighter(0.5, 0.02)), b])["main"]["point"]["regions"][
        "ear"]["effects"]["asperity"]
    assert e["verdict"] == "visible"      # the same difference without noise is resolved


def test02b_a_pair_that_shares_its_samples_shares_its_noise():
    """Two images drawn from the same samples (their noise one realization, each scaled by
    its image): the ratio's noise cancels, so a 2 % effect that independent noise of the
    same size leaves unresolved is visible; with independent realizations the error bar is
    the two noises' sum in quadrature (E[h^2] of the pair's half-difference)."""
    rng = np.random.default_rng(2)
    e = rng.standard_normal((H, W, 3)) * 0.5            # the shared relative noise
    with_, without = ear_brighter(0.5, 0.02), np.full((H, W, 3), 0.5, np.float32)

    def effect(e_a, e_b):
        a = image("asperity", with_, noise=(with_ * e_a).astype(np.float32))
        b = image("lambert", without, noise=(without * e_b).astype(np.float32))
        return run([a, b])["main"]["point"]["regions"]["ear"]["effects"]["asperity"]
    shared = effect(e, e)
    assert shared["verdict"] == "visible" and shared["stderr"] < 1e-6
    other = rng.standard_normal((H, W, 3)) * 0.5
    apart = effect(e, other)
    assert apart["verdict"] == "unresolved"
    # the same as each image's noise alone in quadrature, to the cross term's chance size
    # (800 pixels: the normalised cross sum ~ 1 / sqrt(800) of the squares)
    alone_a = run([image("asperity", with_, noise=(with_ * e).astype(np.float32)),
                   image("lambert", without)])["main"]["point"]["regions"]["ear"][
        "effects"]["asperity"]["stderr"]
    alone_b = run([image("asperity", with_),
                   image("lambert", without, noise=(without * other).astype(np.float32))]
                  )["main"]["point"]["regions"]["ear"]["effects"]["asperity"]["stderr"]
    assert apart["stderr"] == pytest.approx(np.hypot(alone_a, alone_b), rel=5 / np.sqrt(800))


def test03_the_cheapest_adequate_model_is_never_one_that_misses_or_is_unresolved():
    truth = {"point": {"models": {
        # cheapest, but 3 % off in the ear: fails there
        "lafortune": {"seconds": 0.1, "regions": {"ear": {"rel_diff": 0.03, "stderr": 0.002},
                                                   "cheek": {"rel_diff": 0.0, "stderr": 0.001}}},
        # 1.5 % +- 0.5 %: within 2 % but not by two standard errors: unresolved
        "hk93": {"seconds": 0.2, "regions": {"ear": {"rel_diff": 0.015, "stderr": 0.005},
                                              "cheek": {"rel_diff": 0.0, "stderr": 0.001}}},
        "bssrdf": {"seconds": 3.0, "regions": {"ear": {"rel_diff": 0.005, "stderr": 0.002},
                                                "cheek": {"rel_diff": 0.001, "stderr": 0.001}}},
    }}}
    ims = [image(m, 0.5, seconds=truth["point"]["models"][m]["seconds"]) for m in
           ("lafortune", "hk93", "bssrdf")]
    req = run(ims, truth=truth)["main"]["point"]
    ear, cheek = req["regions"]["ear"], req["regions"]["cheek"]
    assert ear["models"]["lafortune"]["verdict"] == "fails"
    assert ear["models"]["hk93"]["verdict"] == "unresolved"
    assert ear["cheapest"] == "bssrdf" and ear["against"] == "reference"
    assert cheek["cheapest"] == "lafortune"
    assert req["cheapest_everywhere"] == "bssrdf"
    # a looser target admits the cheap model everywhere
    loose = run(ims, truth=truth, accuracy=0.05)["main"]["point"]
    assert loose["cheapest_everywhere"] == "lafortune"


def test04_without_a_reference_the_most_complete_model_is_the_truth_and_views_split():
    ims = [image("bssrdf_mc", 0.5, light="point@ear", seconds=5.0),
           image("bssrdf", ear_brighter(0.5, 0.01), light="point@ear", seconds=3.0),
           image("lafortune", ear_brighter(0.5, 0.10), light="point@ear", seconds=0.1),
           image("lafortune", 0.5, light="point", seconds=0.1)]
    req = run(ims)
    assert set(req) == {"main", "ear"}
    ear = req["ear"]["point"]["regions"]["ear"]
    assert ear["against"] == "bssrdf_mc"
    assert ear["models"]["lafortune"]["verdict"] == "fails"
    assert ear["cheapest"] == "bssrdf"
    assert req["ear"]["point"]["regions"]["cheek"]["cheapest"] == "lafortune"
    assert req["main"]["point"]["regions"]["cheek"]["against"] is None


def test05_auto_picks_the_cheapest_measured_model_for_a_loose_target_and_the_best_for_a_tight():
    import tomllib
    from dermis.pipeline.config import scene_from_dict
    from dermis.pipeline.model_choice import EVIDENCE, condition_kind
    from scene_toml import QUICK
    base = tomllib.loads(QUICK.read_text())
    base["render"]["models"] = ["auto"]
    evidence = EVIDENCE[condition_kind(["point"], False)]
    # loose: every model's bound is within it, so the cheapest; tight: none is, so the one
    # with the smallest RMS region error
    for accuracy, want in ((5.0, min(evidence, key=lambda m: evidence[m][0])),
                           (1e-6, min(evidence, key=lambda m: evidence[m][2]))):
        base["report"] = {"accuracy": accuracy}
        s = scene_from_dict(base, where="s.toml")
        assert s.models_of("point") == (want,), (accuracy, s.chosen)
        assert set(s.render.models) == {m for _, m in s.chosen}
    # between the two: a target only some models' bounds meet picks the cheapest of those
    bounds = sorted(b for _, b, _ in evidence.values())
    base["report"] = {"accuracy": bounds[len(bounds) // 2]}
    s = scene_from_dict(base, where="s.toml")
    fits = [m for m, (_, b, _) in evidence.items() if b <= bounds[len(bounds) // 2]]
    assert s.models_of("point") == (min(fits, key=lambda m: evidence[m][0]),)
    base["render"]["models"] = ["auto", "lafortune"]
    with pytest.raises(ConfigError, match='"auto" chooses the models itself'):
        scene_from_dict(base, where="s.toml")


def test06_auto_verdicts_say_whether_the_target_held():
    from dermis.reports.requirements import auto_verdicts
    rows = {"ear": {"against": "reference", "models": {"hk93": {"verdict": "fails"}}},
            "cheek": {"against": "reference", "models": {"hk93": {"verdict": "meets"}}}}
    req = {"main": {"point": {"regions": rows}}}
    assert auto_verdicts(req, {"point": "hk93"}, 0.02)["main"]["point"]["target"] == "missed"
    rows["ear"]["models"]["hk93"]["verdict"] = "meets"
    assert auto_verdicts(req, {"point": "hk93"}, 0.02)["main"]["point"]["target"] == "held"
    rows["ear"]["models"]["hk93"]["verdict"] = "unresolved"
    assert auto_verdicts(req, {"point": "hk93"}, 0.02)["main"]["point"]["target"] == "unresolved"
    for row in rows.values():
        row["against"] = "bssrdf"
    assert auto_verdicts(req, {"point": "hk93"}, 0.02)["main"]["point"]["target"] == "unverified"


def test07_a_region_black_in_both_images_has_no_effect_and_light_only_with_it_is_all_effect():
    black = np.zeros((H, W, 3), np.float32)
    lit_ear = black.copy()
    lit_ear[:, 20:] = 0.5
    rows = run([image("bssrdf", black), image("bssrdf_mc", lit_ear)])["main"]["point"][
        "regions"]
    assert rows["cheek"]["effects"]["profile shape"]["signed"] == 0.0
    assert rows["cheek"]["effects"]["profile shape"]["verdict"] == "absent"
    assert rows["ear"]["effects"]["profile shape"]["signed"] == 1.0
    assert rows["ear"]["effects"]["profile shape"]["verdict"] == "visible"


def test08_a_page_per_view_and_one_more_per_34_rows(tmp_path):
    from matplotlib.backends.backend_pdf import PdfPages
    from dermis.reports.requirement_pages import requirement_lines, requirement_pages
    req = run([image("bssrdf", 0.5), image("bssrdf_mc", ear_brighter(0.5, 0.05)),
               image("bssrdf", 0.5, light="point@ear"),
               image("bssrdf_mc", ear_brighter(0.5, 0.05), light="point@ear")])
    views = {v: {"requires": r} for v, r in req.items()}
    with PdfPages(tmp_path / "r.pdf") as pdf:
        assert requirement_pages(pdf, views, accuracy=0.02, threshold=0.01) == 2
        assert requirement_pages(pdf, views, accuracy=0.02, threshold=0.01, max_rows=2) == 4
    assert requirement_lines(req, "ear") == [
        ("point", "visible: profile shape; cheapest adequate everywhere: "
                  "BSSRDF (Monte Carlo profile)")]
