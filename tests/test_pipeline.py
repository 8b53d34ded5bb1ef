"""The real stage graph on the quick scene: make-style reruns, --until, minimal graphs, CLI."""
import json
from pathlib import Path

import pytest

from dermis.pipeline import api
from dermis.pipeline.cli import main
from dermis.pipeline.config import load_scene
from dermis.pipeline.plan import build_graph

QUICK = Path(__file__).resolve().parents[1] / "scenes" / "quick.toml"


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The quick scene built once into a fresh cache (shared by the tests below)."""
    root = tmp_path_factory.mktemp("quick")
    scene = load_scene(QUICK, overrides={"output": {"output_dir": str(root / "out")}})
    first = api.run(scene, cache=root / "cache")
    return scene, root, first


def test01_first_run_builds_every_requested_stage(built):
    scene, root, first = built
    ran = first.ran()
    assert ran[:7] == ["mesh_source", "mesh_high", "mesh_low", "bake", "mesh_previews",
                       "profiles", "profiles-monte_carlo"]   # bssrdf_mc: the Monte Carlo table
    renders = [r for r in ran if r.startswith("render-")]
    assert len(renders) == 5 * 4 * 3                    # models x lighting x geometries
    assert "render-hk93-dir_left+dir_right-low_bump_blur" in renders
    assert "render-bssrdf-sunset-low_bump" in renders
    assert "render-bssrdf_mc-sunset-low_bump" in renders
    # BSSRDF: points per mesh (not per light), irradiance per mesh and lighting condition
    assert sorted(r for r in ran if r.startswith("samples-")) == ["samples-mesh_high",
                                                                   "samples-mesh_low"]
    assert len([r for r in ran if r.startswith("irradiance-")]) == 2 * 4
    assert ran[-6:] == ["images"] + [f"differences-{l}" for l in ("area", "dir_left+dir_right",
                                                                  "point", "sunset")] + ["report"]
    report = root / "out" / "quick" / "report"
    assert (report / "report.pdf").stat().st_size > 10_000 and (report / "metrics.json").is_file()
    out = root / "out" / "quick"
    assert (out / "run.json").is_file()
    assert sorted(p.name for p in out.glob("mesh_previews/*.png"))  # previews were exported


def test02_second_run_runs_nothing(built):
    scene, root, _ = built
    again = api.run(scene, cache=root / "cache")
    assert again.ran() == []


def test03_one_parameter_reruns_exactly_downstream(built):
    scene, root, _ = built
    blurrier = load_scene(QUICK, overrides={"bake": {"blur_sigma_px": 3.0},
                                            "output": {"output_dir": str(root / "out")}})
    status = {n.id: n for n in api.status(blurrier, cache=root / "cache").nodes}
    assert status["bake"].reasons == ["config_changed blur_sigma_px"]
    assert status["mesh_previews"].reasons == ["upstream_changed bake (stale)"]
    s = api.run(blurrier, cache=root / "cache")
    low_bump = [r for r in s.ran() if r.startswith("render-")]
    assert s.ran()[:2] == ["bake", "mesh_previews"] and s.ran()[-1] == "report"
    assert "images" in s.ran() and len([r for r in s.ran() if r.startswith("differences-")]) == 4
    assert low_bump and all(r.endswith("-low_bump") or r.endswith("-low_bump_blur")
                            for r in low_bump)          # the high-mesh renders stay cached
    assert len(low_bump) == 5 * 4 * 2


def test04_until_builds_only_what_the_stage_needs(built, tmp_path):
    scene, _, _ = built
    s = api.run(scene, cache=tmp_path / "c", until="mesh_high", export=False)
    assert [n.id for n in s.nodes] == ["mesh_source", "mesh_high"]


def test05_graph_holds_only_what_outputs_need():
    brdf_high = load_scene(QUICK, overrides={"render": {"models": ["lafortune"],
                                                        "geometries": ["high"]}})
    nodes, _ = build_graph(brdf_high)
    assert set(nodes) == {"mesh_source", "mesh_high", "mesh_previews", "images"} | {  # no report
        n for l in ("point", "area", "dir_left+dir_right", "sunset")
        for n in (f"render-lafortune-{l}-high", f"visibility-mesh_high-{l}")}
    unbumped = load_scene(QUICK, overrides={"render": {"geometries": ["low"]},
                                            "output": {"previews": False}})
    nodes, _ = build_graph(unbumped)
    assert {n for n in nodes if not n.startswith(("render-", "irradiance-", "visibility-",
                                                  "differences-"))} == {
        "mesh_source", "mesh_high", "mesh_low", "profiles", "profiles-monte_carlo",
        "samples-mesh_low", "images", "report"}
    no_bssrdf = load_scene(QUICK, overrides={"render": {"models": ["lafortune", "hk93"]}})
    nodes, _ = build_graph(no_bssrdf)                   # a BRDF-only run: no points, no profiles
    assert not [n for n in nodes if n.startswith(("samples", "irradiance", "profiles"))]


def test06_cli_run_status_clean(built, capsys):
    scene, root, _ = built
    cache = str(root / "cache")
    assert main(["run", str(QUICK), "--cache", cache, "-q"]) == 0
    out = capsys.readouterr().out
    assert "mesh_source" in out and "cached" in out and " ran " not in out
    assert main(["status", str(QUICK), "--cache", cache]) == 0
    # 66 + 8 visibilities + 4 diffs + 12 bssrdf_mc images and their Monte Carlo table
    assert "0 of 91 stages stale" in capsys.readouterr().out
    assert main(["run", str(QUICK), "--cache", cache, "--until", "nope"]) == 2
    capsys.readouterr()
    assert main(["clean", "--cache", cache, "--stage", "profiles"]) == 0
    assert "removed 2" in capsys.readouterr().out        # profiles and profiles-monte_carlo
    assert main(["status", str(QUICK), "--cache", cache]) == 0
    assert "profiles" in capsys.readouterr().out


def test07_metadata_has_timing_and_device(built):
    _, root, first = built
    rep = {r.id: r for r in first.nodes}["mesh_high"]
    meta = json.loads((Path(rep.path) / "meta.json").read_text())
    assert meta["seconds"] > 0 and meta["parts"]["params"]["target_triangles"] == 60_000


def test08_results_kept_across_runs_by_content():
    """pipeline/reuse.py: keys follow content (dtype, shape, bytes), the oldest result goes
    first, and an equal mesh loaded again (a new run) finds its Embree scene."""
    import numpy as np
    from dermis.pipeline.reuse import RecentResults, content_key
    from dermis.lighting import visibility
    a = np.arange(6, dtype=np.float32)
    assert content_key(a) == content_key(a.copy())
    assert len({content_key(a), content_key(a.astype(np.float64)), content_key(a.reshape(2, 3)),
                content_key(a + 1), content_key(a, 1)}) == 5
    made = []
    keep = RecentResults(2)
    for k in (1, 2, 1, 3, 1, 2):
        keep.get(k, lambda: made.append(k))
    assert made == [1, 2, 3, 2]                 # 2 was dropped when 3 came (1 used since)

    class Mesh:                                 # what shared() reads of a mesh
        def __init__(self):
            self.vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
            self.faces = np.array([[0, 1, 2]], np.int32)
    from dermis.pipeline.shared import RunCache
    cache = RunCache()                          # one cache kept across the runs
    first = visibility.embree_scene(Mesh(), cache)
    assert visibility.embree_scene(Mesh(), cache) is first
    other = Mesh()
    other.vertices = other.vertices * 2.0
    assert visibility.embree_scene(other, cache) is not first


def _differing_artifacts(first, second) -> tuple[list[str], int]:
    """(files whose bytes differ between two runs' nodes, files compared).  What prints the
    seconds a node took differs by those alone: JSON files are compared without their time
    measurements, and the contact sheets, the PDF (timings in the captions) and the report page
    (timings beside the images) are left out."""
    from dermis.pipeline.graph import _split
    assert [n.id for n in second.nodes] == [n.id for n in first.nodes]
    differ, compared = [], 0
    for a, b in zip(first.nodes, second.nodes):
        assert a.key == b.key, a.id
        sums_a = json.loads((Path(a.path) / "meta.json").read_text())["checksums"]
        sums_b = json.loads((Path(b.path) / "meta.json").read_text())["checksums"]
        assert sorted(sums_a) == sorted(sums_b), a.id
        for name in sums_a:
            if name.startswith("sheet-") or name in ("report.pdf", "report.html"):
                continue
            if name.endswith(".json") and sums_a[name] != sums_b[name]:
                ja, jb = (json.loads((Path(n.path) / name).read_text()) for n in (a, b))
                same = (_split(ja)[0] == _split(jb)[0]) if isinstance(ja, dict) else ja == jb
            else:
                same = sums_a[name] == sums_b[name]
            compared += 1
            if not same:
                differ.append(f"{a.id}/{name}")
    return differ, compared


def test09_nodes_run_at_once_give_the_same_bytes_as_one_by_one(built, tmp_path):
    """The default jobs (2 threads) and one node at a time, each into a fresh cache, must
    give every node the same key and every artifact the same bytes."""
    scene = built[0]
    assert api.resolve_jobs() >= 2
    first = api.run(scene, cache=tmp_path / "at_once", export=False)
    serial = api.run(scene, cache=tmp_path / "one_by_one", export=False, jobs=1)
    differ, compared = _differing_artifacts(first, serial)
    assert compared > 200 and differ == [], differ


@pytest.mark.slow
def test09b_four_threads_again_and_again_give_the_same_bytes(built, tmp_path):
    """Four nodes at once, three times into fresh caches: the run's shared intermediates
    (pipeline/shared.py) are made once whoever asks first, so every artifact has the bytes of
    the one-node-at-a-time run, whatever order the threads take."""
    scene = built[0]
    serial = api.run(scene, cache=tmp_path / "one_by_one", export=False, jobs=1)
    for k in range(3):
        again = api.run(scene, cache=tmp_path / f"four_{k}", export=False, jobs=4)
        differ, compared = _differing_artifacts(serial, again)
        assert compared > 200 and differ == [], (k, differ)


def _ask_at_once(ask, askers: int = 4):
    """``ask(make)`` from ``askers`` threads at once; returns (made, results): ``make`` counts
    its calls and takes long enough for every asker to arrive meanwhile."""
    import threading
    import time
    made, got = [], []

    def make():
        made.append(1)
        time.sleep(0.2)
        return object()

    threads = [threading.Thread(target=lambda: got.append(ask(make))) for _ in range(askers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return made, got


def test10_concurrent_askers_of_one_result_share_one_computation():
    """RecentResults (pipeline/reuse.py): threads asking for the same missing key at once make
    it once (two nodes on two threads need the same Embree scene)."""
    from dermis.pipeline.reuse import RecentResults
    keep = RecentResults(2)
    made, got = _ask_at_once(lambda make: keep.get("k", make))
    assert len(made) == 1 and len(got) == 4 and len({id(g) for g in got}) == 1


def test10b_run_intermediates_are_made_once_by_concurrent_nodes():
    """pipeline/shared.py: an intermediate asked for by four threads at once is made once, and
    a later ask gets it without making (two BSSRDF nodes started together each located the
    same shadow edges before, subsurface/exitance.py)."""
    from dermis.pipeline.shared import RunCache, Shared
    edges, run = Shared("edges"), RunCache()
    made, got = _ask_at_once(lambda make: run.get(edges, ("k", 1), make))
    assert len(made) == 1 and len(got) == 4 and len({id(g) for g in got}) == 1
    assert run.get(edges, ("k", 1), lambda: 1 / 0) is got[0]
    assert run.get(edges, ("k", 2), object) is not got[0]


def test11_jobs_are_checked():
    from dermis.pipeline.errors import DermisError
    for bad in (0, "two", 65, "1.5"):
        with pytest.raises(DermisError, match="whole number from 1 to 64"):
            api.resolve_jobs(bad)
    assert api.resolve_jobs(3) == 3
