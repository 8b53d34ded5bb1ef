"""Layer profiles against dermis's own Monte Carlo (docs/profiles.md).

Each case runs the OpenCL Monte Carlo inside the test with few photons.  A tolerance is the
model error measured with 1e6 photons (docs/profiles.md, stated per test) plus 3 standard
errors of the run here, and never more than 10 %.  The Monte Carlo table model
(``[optics] profile = "monte_carlo"``) is checked against the totals it came from, against
a second seed and against the multipole's fields and units.
"""
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline.artifacts import LayerProfile
from dermis.optics.layers import PRESETS, LayerStack, load_layers_toml
from dermis.optics import monte_carlo_slab as M
from dermis.optics.layer_profiles import MultipoleOptions, build_profiles
from dermis.optics.monte_carlo_table import MC_W_MIN
from dermis.stages import profiles as P

LAYERS = Path(__file__).resolve().parents[1] / "scenes" / "layers"
DIFFUSION_LIMIT = 0.10          # the bound on every diffusion error tested here


def stack(name: str) -> LayerStack:
    return load_layers_toml(LAYERS / f"{name}.toml")


def tolerance(model_error: float, se: np.ndarray) -> np.ndarray:
    tol = model_error + 3.0 * np.asarray(se)
    assert np.all(tol <= DIFFUSION_LIMIT), (model_error, se)
    return tol


def mc_rings(st, edges, photons, seed=1, window=None):
    return M.simulate(st, photons=photons, edges=np.asarray(edges, float), seed=seed,
                      weight_window=M.WeightWindow(window))


def ring_energy(prof, edges):
    from dermis.optics.profile_command import ring_energy as re
    return re(prof, np.asarray(edges, float))


@pytest.fixture(scope="module")
def env():
    from dermis.pipeline import cl as dcl
    try:
        return dcl.get_env()
    except Exception as exc:  # pragma: no cover
        pytest.skip(f"no OpenCL device: {exc}")


# ---- 01 the fixed cases -------------------------------------------------------------
def test01_two_layer_skin_Rd(env):
    # issue: +39.5 % (dermis <= 1: +37 % here).  Measured with 1e6 photons: within 0.3 %
    # (the totals are the exact plane-parallel ones); stated model error 2 %.
    st = stack("two_layer_skin")
    prof = build_profiles(st, options=MultipoleOptions(grid=(0.05, 8.0)))
    mc = M.simulate(st, photons=60000, r_max_mm=5, bins=5, seed=2)
    err = prof.Rd / mc.Rd - 1
    assert np.all(np.abs(err) < tolerance(0.02, mc.Rd_err / mc.Rd)), err
    old = build_profiles(st, options=MultipoleOptions(grid=(0.05, 8.0), diffusion="dj2005"))
    assert old.Rd[0] / mc.Rd[0] - 1 > 0.3          # dermis <= 1's failure, for the record


def test02_two_layer_preset_Rd(env):
    # issue: +21-22 %.  Measured: within 0.2 %; stated 2 %.
    st = PRESETS["two_layer"]
    prof = build_profiles(st, options=MultipoleOptions(grid=(0.05, 8.0)))
    mc = M.simulate(st, photons=60000, r_max_mm=5, bins=5, seed=3)
    err = prof.Rd / mc.Rd - 1
    assert np.all(np.abs(err) < tolerance(0.02, mc.Rd_err / mc.Rd)), err


@pytest.mark.parametrize("name", ["thin_epidermis", "thin_epidermis_from_below"])
def test03_thin_epidermis_R_and_T(env, name):
    # issue: R +98 %, lit from below R -20 %, T +18 %.  Measured: within 1.5 % (R) and
    # 0.5 % (T); stated 3 % and 1 %.
    st = stack(name)
    prof = build_profiles(st)
    mc = M.simulate(st, photons=100000, r_max_mm=5, bins=5, seed=4)
    eR, eT = prof.Rd / mc.Rd - 1, prof.Tt / mc.Tt - 1
    assert np.all(np.abs(eR) < tolerance(0.03, mc.Rd_err / mc.Rd)), eR
    assert np.all(np.abs(eT) < tolerance(0.01, mc.Tt_err / mc.Tt)), eT
    # the unscattered part uses the full extinction: e^{-sigma_t d}, not e^{-sigma_t' d}
    lay = st.layers[0]
    tau = np.exp(-(np.array(lay.sigma_a) + np.array(lay.sigma_s)) * lay.thickness_mm)
    assert np.all(np.array(prof.info["T_ballistic"]) < 1.01 * tau)


def test04_slab_1mm_profile(env):
    # dermis <= 1: R(r) +12 % at 2 mm (red).  Rings [0.5, 1], [1, 2] mm; measured with
    # 1e6 photons: red -1 %, +5 %; green +2 %, +7 %; blue +5 %, +9 % (diffusion's slab tail
    # falls too slowly: docs/profiles.md).  Stated 7 % for red and green; blue is held to the
    # 10 % bound plus its noise.
    st = stack("slab_1mm")
    prof = build_profiles(st)
    edges = [0.0, 0.5, 1.0, 2.0]
    mc = mc_rings(st, edges, 300000, seed=5)
    area = np.pi * np.diff(np.asarray(edges) ** 2)
    e_mc = mc.R * area[:, None]
    se = mc.R_err * area[:, None] / e_mc
    err = ring_energy(prof, edges) / e_mc - 1
    assert np.all(np.abs(err[1:, :2]) < tolerance(0.07, se[1:, :2])), err[1:]
    assert np.all(np.abs(err[1:, 2]) < DIFFUSION_LIMIT + 3 * se[1:, 2]), err[1:]
    assert np.all(np.abs(prof.Rd / mc.Rd - 1) < tolerance(0.01, mc.Rd_err / mc.Rd))
    assert np.all(np.abs(prof.Tt / mc.Tt - 1) < tolerance(0.015, mc.Tt_err / mc.Tt))


def test05_low_albedo_beats_the_dipole(env):
    # reduced albedo 0.91 (red): the dipole is +9 %; the default model is kept because it
    # is closer to the Monte Carlo in every channel (measured: +0.2 %, -0.0 %, -0.1 %)
    st = stack("low_albedo")
    new = build_profiles(st)
    old = build_profiles(st, options=MultipoleOptions(diffusion="dj2005"))
    mc = M.simulate(st, photons=100000, r_max_mm=5, bins=5, seed=6)
    assert old.Rd[0] / mc.Rd[0] - 1 > 0.05
    assert np.all(np.abs(new.Rd / mc.Rd - 1) < np.abs(old.Rd / mc.Rd - 1))
    assert np.all(np.abs(new.Rd / mc.Rd - 1) < tolerance(0.01, mc.Rd_err / mc.Rd))


# ---- 02 the Monte Carlo table ---------------------------------------------------------
@pytest.fixture(scope="module")
def mc_tables(env):
    st = PRESETS["two_layer"]
    a = build_profiles(st, model="monte_carlo", photons=30000, seed=11, env=env)
    b = build_profiles(st, model="monte_carlo", photons=30000, seed=12, env=env)
    return st, a, b


def test06_table_is_a_layer_file(mc_tables):
    st, a, _ = mc_tables
    mp = build_profiles(st, options=MultipoleOptions(grid=(0.05, 8.0)))
    assert isinstance(a, LayerProfile)
    assert [f.name for f in dataclasses.fields(a)] == [f.name for f in dataclasses.fields(mp)]
    n = len(a.r_mm)
    assert a.R.shape == a.T.shape == (n, 3) and a.r_mm[0] == 0 and np.all(np.diff(a.r_mm) > 0)
    for x in (a.Rd, a.Tt, a.cutoff_mm, a.energy_beyond_cutoff):
        assert x.shape == (3,)
    # the same units: ring averages in 1/mm^2 that integrate to Rd, and the same physics
    # (R(r) within 15 % of the multipole's over 0.3-2 mm, Rd within 2 %)
    e = np.asarray(a.info["r_edges"])
    inside = (a.R * (np.pi * np.diff(e**2))[:, None]).sum(0)
    # (float32 ring sums against float32 totals: 1e-7)
    np.testing.assert_allclose(inside, a.Rd * (1 - np.array(a.info["energy_beyond_table"])),
                               rtol=1e-5)
    assert np.all(np.abs(a.Rd / mp.Rd - 1) < 0.02)
    rings = [0.3, 0.5, 0.8, 1.2, 2.0]
    assert np.all(np.abs(ring_energy(a, rings) / ring_energy(mp, rings) - 1) < 0.15)
    assert len(a.info["R_err"]) == n and np.all(np.asarray(a.info["R_err"]) >= 0)
    assert "per photon that entered" in a.info["convention"]


def test07_table_Rd_is_the_monte_carlo_total(mc_tables, env):
    # the table's totals are those of the runs it came from (the pilot and the main run:
    # same seeds, photons per channel, rings and window), pooled
    st, a, _ = mc_tables
    runs = a.info["runs"]
    assert len(runs) == 2 and runs[1]["seed"] == 11 and runs[0]["seed"] != 11
    # the budget: 3 x 30000 photons in all, shared unequally
    assert abs(sum(np.sum(r["photons_per_channel"]) for r in runs) - 90000) < 0.02 * 90000
    assert len(set(runs[1]["photons_per_channel"])) > 1
    mc = [M.simulate(st, photons=r["photons_per_channel"], edges=np.asarray(a.info["r_edges"]),
                     seed=r["seed"], batches=a.info["batches"], env=env,
                     weight_window=M.WeightWindow(a.info["window"], MC_W_MIN)) for r in runs]
    mc = M.combine(*mc)
    np.testing.assert_array_equal(a.Rd, mc.Rd)
    np.testing.assert_array_equal(a.Tt, mc.Tt)
    np.testing.assert_array_equal(a.R, mc.R)
    np.testing.assert_array_equal(a.info["Rd_err"], mc.Rd_err)


def test08_two_seeds_agree_within_their_noise(mc_tables):
    # 12 log rings over [0.05, 5] mm per channel: z = difference / combined standard error;
    # with 16 batches the errors are themselves estimates (t with 15 degrees of freedom)
    _, a, b = mc_tables
    edges = np.geomspace(0.05, 5.0, 13)

    def binned(p):
        own = np.asarray(p.info["r_edges"])
        area = np.pi * np.diff(own**2)[:, None]
        var = np.vstack([np.zeros(3), np.cumsum((np.asarray(p.info["R_err"]) * area) ** 2, 0)])
        v = np.diff(np.stack([np.interp(edges, own, var[:, c]) for c in range(3)], 1), axis=0)
        return ring_energy(p, edges), np.sqrt(v)

    (ea, sa), (eb, sb) = binned(a), binned(b)
    z = (ea - eb) / np.hypot(sa, sb)
    assert np.abs(z).max() < 5.0 and 0.2 < np.mean(z**2) < 3.0, z
    zt = (a.Rd - b.Rd) / np.hypot(a.info["Rd_err"], b.info["Rd_err"])
    assert np.all(np.abs(zt) < 5.0)


def test09_splitting_is_unbiased(env):
    # the weight window changes the noise, not the answer: analog and split runs agree on
    # the totals and on rings out to where the analog run still has light (5 sigma)
    st = stack("slab_1mm")
    edges = [0.0, 0.2, 0.5, 1.0, 2.0, 3.0]
    window = [[1.5, 0.3, 3.0, 0.5], [3.0, 0.2, 3.0, 1.0], [4.0, 0.1, 3.0, 1.5]]
    a = mc_rings(st, edges, 60000, seed=7)
    b = M.simulate(st, photons=60000, edges=np.asarray(edges, float), seed=8,
                   weight_window=M.WeightWindow(window, 0.25), env=env)
    assert np.all(np.abs(a.Rd - b.Rd) < 5 * np.hypot(a.Rd_err, b.Rd_err))
    assert np.all(np.abs(a.Tt - b.Tt) < 5 * np.hypot(a.Tt_err, b.Tt_err))
    ok = a.R > 10 * a.R_err
    z = (a.R - b.R)[ok] / np.hypot(a.R_err, b.R_err)[ok]
    assert np.abs(z).max() < 5.0, z


# ---- 03 the stage and the scene keys ----------------------------------------------------
def test10_optics_profile_keys(tmp_path):
    import tomllib
    from dermis.pipeline.config import scene_from_dict
    from dermis.pipeline.errors import ConfigError
    scene_file = Path(__file__).resolve().parents[1] / "scenes" / "quick.toml"
    t = tomllib.loads(scene_file.read_text())
    t["optics"] = {"preset": "two_layer", "profile": "monte_carlo", "photons": 50000, "seed": 3}
    s = scene_from_dict(t, where=str(scene_file))
    n = P.node(s)
    assert n.params["model"] == "monte_carlo" and n.params["photons"] == 50000
    assert n.params["seed"] == 3 and n.params["stack"] == PRESETS["two_layer"].to_dict()
    t["optics"] = {"preset": "two_layer"}
    n0 = P.node(scene_from_dict(t, where=str(scene_file)))
    assert n0.params == {"stack": PRESETS["two_layer"].to_dict(), "model": "multipole"}
    t["optics"] = {"preset": "two_layer", "profile": "monte-carlo", "photons": 0}
    with pytest.raises(ConfigError, match=r"optics\.profile = 'monte-carlo': must be one of "
                                          r"\"multipole\", \"monte_carlo\".*\n.*optics\.photons = 0"):
        scene_from_dict(t, where=str(scene_file))


def test11_stage_runs_the_chosen_model(env):
    class Ctx:
        cl = env
        progress = None
    params = {"stack": PRESETS["skin2"].to_dict(), "model": "monte_carlo", "photons": 20000,
              "seed": 1}
    res = P.run(params, {}, Ctx())
    assert res.artifact.info["model"] == "monte_carlo" and res.info["kernel_seconds"] > 0
    res = P.run({"stack": PRESETS["skin2"].to_dict(), "model": "multipole"}, {}, Ctx())
    assert res.artifact.info["model"] == "multipole"


# ---- 04 the BSSRDF with the Monte Carlo profile beside the multipole one ------------------
def _quick(models, optics=None):
    import tomllib
    from dermis.pipeline.config import scene_from_dict
    scene_file = Path(__file__).resolve().parents[1] / "scenes" / "quick.toml"
    t = tomllib.loads(scene_file.read_text())
    t["render"]["models"] = list(models)
    if optics is not None:
        t["optics"] = optics
    return scene_from_dict(t, where=str(scene_file))


def _keys(scene):
    from dermis.pipeline import codehash
    from dermis.pipeline.graph import key_parts, node_key, plan_order
    from dermis.pipeline.plan import build_graph
    codehash.clear()
    nodes, targets = build_graph(scene)
    keys = {}
    for nid in plan_order(nodes, list(nodes)):
        keys[nid] = node_key(key_parts(nodes[nid], keys))
    return nodes, targets, keys


def test12_bssrdf_mc_shares_everything_but_the_profile():
    from dermis.pipeline.scene_rules import scene_warnings
    scene = _quick(["lafortune", "bssrdf", "bssrdf_mc"])
    nodes, targets, keys = _keys(scene)
    labels = [label for label, _ in scene.light_groups()]
    pairs = [(f"render-bssrdf-{l}-{g}", f"render-bssrdf_mc-{l}-{g}")
             for l in labels for g in scene.render.geometries]
    assert len(pairs) == 12
    for a, b in pairs:
        da, db = dict(nodes[a].deps), dict(nodes[b].deps)
        assert da.pop("profile") == "profiles" and db.pop("profile") == "profiles-monte_carlo"
        # the same points, irradiance, visibility (and mesh, maps) nodes: only the profile differs
        assert da == db and {"points", "irradiance", "visibility"} <= set(da), (a, da)
        assert nodes[b].params == {**nodes[a].params, "model": "bssrdf_mc"}
        assert keys[a] != keys[b]
    assert nodes["profiles"].params["model"] == "multipole"
    mc = nodes["profiles-monte_carlo"].params
    assert mc["model"] == "monte_carlo" and mc["photons"] == scene.optics.photons == 200_000
    assert keys["profiles"] != keys["profiles-monte_carlo"]
    assert {"profiles", "profiles-monte_carlo"} <= set(targets)
    # each shared node exists once: one per mesh (points) or mesh x lighting condition
    assert sum(n.stage == "irradiance" for n in nodes.values()) == 2 * len(labels)
    assert sum(n.stage == "visibility" for n in nodes.values()) == 2 * len(labels)
    # adding bssrdf_mc leaves every other node's key as it was
    _, _, plain = _keys(_quick(["lafortune", "bssrdf"]))
    for nid, k in plain.items():
        if nid not in ("images", "report") and not nid.startswith("differences-"):
            assert keys[nid] == k, nid
    # the images, the differences (against the multipole bssrdf) and the report list it
    mc_ids = {b for _, b in pairs}
    assert mc_ids <= set(nodes["images"].dep_ids)
    for l in labels:
        diff = nodes[f"differences-{l}"]
        assert {b for a, b in pairs if f"-{l}-" in b} <= set(diff.dep_ids)
    assert mc_ids <= set(nodes["report"].dep_ids)
    assert {"profiles", "profiles-monte_carlo"} <= set(nodes["report"].dep_ids)
    assert not scene_warnings(scene)
    # a Monte Carlo scene profile: bssrdf_mc reads the same table (one node) and is warned of
    same = _quick(["bssrdf", "bssrdf_mc"], optics={"preset": "two_layer",
                                                   "profile": "monte_carlo", "photons": 1000})
    n2, _, _ = _keys(same)
    assert "profiles-monte_carlo" not in n2 and n2["profiles"].params["model"] == "monte_carlo"
    assert n2["render-bssrdf_mc-point-high"].deps["profile"] == "profiles"
    assert any("same image" in w for w in scene_warnings(same))


def test13_bssrdf_mc_is_a_scene_model():
    from dermis.models.catalog import label
    from dermis.pipeline.config import RenderConfig
    from dermis.pipeline.errors import ConfigError
    from dermis.pipeline.registry import model_names
    assert "bssrdf_mc" in model_names() and "bssrdf_mc" not in RenderConfig().models   # opt-in
    assert label("bssrdf_mc") == "BSSRDF (Monte Carlo profile)"
    with pytest.raises(ConfigError, match=r"render\.models.*bssrdf_mc"):
        _quick(["bssrdf_mk"])


# ---- 05 thin layers: where the direct light lands ----------------------------------------
# A thin layer passes much of its light on scattered forward; as a delta at r = 0 the layer
# file put 90 % of thin_epidermis's T beyond 0.05 mm in the wrong place (optics/
# forward_spread.py; docs/profiles.md "Thin layers").  The fraction of the total on
# [0.05, 2] mm against the Monte Carlo, per channel R / G / B, measured with 2e6 photons
# (bench/bench_thin_layers.py, bench/results/thin_layers.json):
#   thin_epidermis T: model 0.619 / 0.615 / 0.609, MC 0.600 / 0.586 / 0.563 (as a delta:
#     0.063 / 0.073 / 0.102);
#   thin_epidermis_from_below R: 0.945 / 0.947 / 0.949 against 0.926 / 0.915 / 0.888
#     (as a delta: 0.544 / 0.578 / 0.665), T: 0.527 / 0.525 / 0.524 against
#     0.473 / 0.463 / 0.448 (0.051 / 0.055 / 0.073).
# Stated model errors (absolute, on the fraction): 0.05 (T), 0.07 (R from below), 0.08 (T
# from below), plus 3 standard errors of the run here.
@pytest.mark.parametrize("name, field, model_error", [
    ("thin_epidermis", "T", 0.05),
    ("thin_epidermis_from_below", "R", 0.07),
    ("thin_epidermis_from_below", "T", 0.08)])
def test05_thin_layer_light_lands_where_the_monte_carlo_puts_it(env, name, field, model_error):
    st = stack(name)
    prof = build_profiles(st)
    edges = [0.0, 0.05, 2.0, 20.0]
    mc = mc_rings(st, edges, 200000, seed=7)
    area = np.pi * np.diff(np.asarray(edges) ** 2)
    total = mc.Rd if field == "R" else mc.Tt
    e_mc = (mc.R if field == "R" else mc.T)[1] * area[1]
    se = (mc.R_err if field == "R" else mc.T_err)[1] * area[1] / total
    from dermis.optics.profile_command import ring_energy as re
    mine = re(prof, np.asarray(edges[:3]), field)[1] / (prof.Rd if field == "R" else prof.Tt)
    err = mine - e_mc / total
    assert np.all(np.abs(err) < tolerance(model_error, se)), (mine, e_mc / total)
