"""Structure: import directions, one module per stage, and cache keys that cover the code run.

The key probe appends a harmless comment to a source file (through the hashing seam
``codehash.read_source``, so the repository is never touched) and checks that exactly the
nodes that execute that file get new keys.  The expected sets are written out by hand from
what each stage runs, so a closure that misses a file (or drags one in) fails here.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

import dermis
from dermis.pipeline import codehash
from dermis.pipeline.config import load_scene
from dermis.pipeline.graph import key_parts, node_key, plan_order
from dermis.pipeline.plan import build_graph
from dermis.pipeline.registry import STAGE_NAMES, stage

REPO = Path(__file__).resolve().parents[1]
QUICK = REPO / "scenes" / "quick.toml"


def _imports(path: Path) -> set[str]:
    """Every module named by an import statement anywhere in ``path`` (relative ones resolved)."""
    rel = path.relative_to(REPO).with_suffix("")
    package = ["dermis", *rel.parts[:-1]]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out


# the packages by concept: libraries that stages adapt into nodes
LIBRARIES = ("geometry", "optics", "subsurface", "lighting", "rendering", "models",
             "groundtruth", "reports")


def test01_engine_imports_no_stage_report_or_physics():
    """The engine reaches stages and models only by name (pipeline/registry.py)."""
    bad = {}
    for path in sorted((REPO / "pipeline").glob("*.py")):
        up = sorted(m for m in _imports(path) if m.startswith(
            tuple(f"dermis.{p}" for p in ("stages",) + LIBRARIES)))
        if up:
            bad[path.name] = up
    assert not bad, f"engine modules import stages or libraries: {bad}"


def test02_libraries_import_no_stage():
    bad = {}
    for package in LIBRARIES:
        assert (REPO / package / "__init__.py").is_file(), package
        for path in sorted((REPO / package).glob("*.py")):
            up = [m for m in _imports(path) if m.startswith("dermis.stages")]
            if up:
                bad[f"{package}/{path.name}"] = up
    assert not bad, f"libraries import stages: {bad}"


def test02b_package_modules_stay_small_and_stages_thin():
    """No package module over ~800 lines; a stage module is an adapter (node, plan, run)."""
    big = {str(p.relative_to(REPO)): n for package in ("pipeline",) + LIBRARIES
           for p in (REPO / package).glob("*.py")
           if (n := len(p.read_text().splitlines())) > 800}
    assert not big, big
    fat = {p.name: n for p in (REPO / "stages").glob("*.py")
           if (n := len(p.read_text().splitlines())) > 200}
    assert not fat, fat


def test03_every_stage_is_one_module_owning_its_node():
    assert STAGE_NAMES == tuple(name for name, _ in dermis.STAGES)
    for name in STAGE_NAMES:
        mod = stage(name)
        assert mod.NAME == name, mod.__name__
        assert isinstance(mod.VERSION, int) and isinstance(mod.KERNELS, tuple)
        assert callable(mod.node) and callable(mod.run)
    nodes, _ = build_graph(load_scene(QUICK))
    for node in nodes.values():  # every node runs the module of its own stage
        assert node.module == dict(dermis.STAGES)[node.stage], node.id
        assert node.fn is None


def test04_readme_stage_table_lists_exactly_the_stages():
    rows = [line.split("|")[1].strip().strip("`") for line in
            (REPO / "README.md").read_text().splitlines() if line.lstrip().startswith("| `")]
    assert [r for r in rows if not r.startswith("[")] == list(STAGE_NAMES)


def test05_the_wheel_installs_one_top_level_name(wheel):
    """Read what the built wheel would install: only ``dermis/`` and its metadata."""
    import zipfile
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {"dermis", next(t for t in tops if t.endswith(".dist-info"))}, tops
    for must in ("dermis/__init__.py", "dermis/pipeline/api.py", "dermis/optics/fresnel.py",
                 "dermis/stages/bssrdf.py", "dermis/reports/pdf_report.py", "dermis/cl/common.h",
                 "dermis/scenes/default.toml", "dermis/scenes/layers/two_layer.toml"):
        assert must in names, must
    assert not [n for n in names if n.startswith(("dermis/tests/", "dermis/bench/"))]
    entry = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt")))
    assert b"dermis = dermis.pipeline.cli:main" in entry


# ------------------------------------------------------------------------------ key probe
def _keys(scene) -> dict[str, str]:
    codehash.clear()
    nodes, targets = build_graph(scene)
    keys = {}
    for nid in plan_order(nodes, list(nodes)):
        keys[nid] = node_key(key_parts(nodes[nid], keys))
    return keys


@pytest.fixture(scope="module")
def scene():
    return load_scene(QUICK)


@pytest.fixture(scope="module")
def base_keys(scene):
    return _keys(scene)


def _runs(node, spec: set) -> bool:
    """Whether ``node`` is named by ``spec``: its stage ("render"), or its stage and the model
    it renders ("render/hk93": a render node looks its model up in the registry and hashes
    that model's module, pipeline/graph.py Node.code)."""
    return node.stage in spec or f"{node.stage}/{node.params.get('model')}" in spec


# file -> the stages whose nodes execute it (from what each stage runs, written out by hand)
PROBE = {
    "cl/surface.cl": {"render", "bssrdf", "visibility"},  # hit attributes: rays + images
    "cl/optics.h": {"render", "bssrdf"},               # Fresnel in HK93 (cl/shade.cl includes it)
    "cl/bssrdf_gather.cl": {"bssrdf"},
    "stages/render.py": {"render"},                    # others read GEOMETRY when planning
    # the BSSRDF's surface lobes and the entry transmittance they cap; a term's bases
    "models/lafortune.py": {"render/lafortune", "render/asperity", "bssrdf", "irradiance",
                            "visibility"},             # and the lobes the rays sample
    "models/hk93.py": {"render/hk93", "render/asperity"},   # only the images of its model
    # the previews cast their rays on the renders' shared Embree scenes (lighting/visibility.py)
    "lighting/visibility.py": {"render", "bssrdf", "irradiance", "visibility", "mesh_previews",
                               "report"},             # the report's regions cast camera rays
    "lighting/strata.py": {"render", "bssrdf", "irradiance", "visibility", "report"},
    "rendering/camera.py": {"render", "bssrdf", "visibility", "report"},
    "geometry/normals.py": {"mesh_source", "mesh_high", "mesh_low", "bake", "mesh_previews",
                            "visibility", "render", "bssrdf"},
    "lighting/warps.py": {"render", "bssrdf", "irradiance", "visibility"},
    "lighting/emitters.py": {"render", "bssrdf", "irradiance", "visibility"},
    "lighting/environment.py": {"render", "bssrdf", "irradiance", "visibility"},
    "lighting/lobes.py": {"render", "bssrdf", "visibility"},   # the irradiance pass draws none
    # the renderer's environment estimator, imported with the light sampling everywhere
    "lighting/mixture.py": {"render", "bssrdf", "irradiance", "visibility"},
    "lighting/control.py": {"render", "bssrdf", "irradiance", "visibility"},
    "lighting/irradiance.py": {"irradiance", "bssrdf"},   # the gather's shadow edges use it
    "rendering/cast.py": {"visibility", "render", "bssrdf"},   # shared rays, hit attributes
    # the bounce itself: only the irradiance points read it when no indirect node is planned;
    # the BRDF response reads no ray-tracing code of it (lighting/visibility.py interpolate)
    "lighting/indirect.py": {"irradiance"},
    "rendering/indirect_shading.py": {"render", "bssrdf"},   # the BSSRDF's surface lobes
    "pipeline/plan.py": set(),                         # decides which nodes exist, runs in none
    # the scene schema: its dataclasses and defaults are what stages rebuild their config from
    "pipeline/config.py": {"irradiance", "visibility", "render", "bssrdf", "report"},
    "pipeline/scene_rules.py": set(),                  # accepts or refuses a scene, runs in none
    "pipeline/shared.py": {"mesh_previews", "irradiance", "visibility", "render", "bssrdf",
                           "report"},
    "reports/diff.py": {"report", "differences"},
    "reports/sheets.py": {"images", "report", "differences",   # grids drawn with Pillow
                          "mesh_previews"},                  # and its PNG writer
    "reports/tonemap.py": {"images", "report"},        # tone mapping is not part of rendering
    "reports/page/page.js": {"report"},                # the report page's data files (DATA_FILES)
    "subsurface/exitance.py": {"bssrdf"},
    "subsurface/points.py": {"samples", "bssrdf"},     # the gather reads the kernel width
    "geometry/validation.py": {"mesh_source"},
    "geometry/subdivision.py": {"mesh_high", "mesh_low"},   # uv_transfer reads its corner pairs
    "geometry/simplification.py": {"mesh_low"},
    "geometry/uv_transfer.py": {"mesh_low"},
}


@pytest.mark.parametrize("relpath", sorted(PROBE))
def test06_a_harmless_edit_changes_exactly_the_keys_of_nodes_that_run_it(relpath, scene,
                                                                         base_keys, monkeypatch):
    target = (REPO / relpath).resolve()
    assert target.is_file()
    original = codehash.read_source

    def edited(path):
        data = original(path)
        comment = b"\n# probe\n" if target.suffix == ".py" else b"\n// probe\n"
        return data + comment if Path(path).resolve() == target else data

    monkeypatch.setattr(codehash, "read_source", edited)
    changed = {nid for nid, k in _keys(scene).items() if base_keys[nid] != k}
    monkeypatch.undo()
    codehash.clear()
    nodes, _ = build_graph(scene)
    direct = {nid for nid in base_keys if _runs(nodes[nid], PROBE[relpath])}
    # a changed node changes its downstream nodes' keys too (their upstream keys changed)
    expected, grew = set(direct), True
    while grew:
        more = {nid for nid, n in nodes.items() if set(n.dep_ids) & expected} - expected
        expected |= more
        grew = bool(more)
    if PROBE[relpath]:
        assert direct, f"no node of {PROBE[relpath]} in the quick scene"
    assert changed == expected, (f"{relpath}: unexpected {sorted(changed - expected)[:5]}, "
                                 f"missed {sorted(expected - changed)[:5]}")


def test07_closure_follows_function_local_imports():
    closure = codehash.module_closure("dermis.stages.mesh_source")
    # the procedural head and the scan reader, and the modules they import in turn
    assert "dermis.geometry.procedural_head" in closure and "dermis.geometry.mesh_formats" in closure
    assert "dermis.pipeline.graph" not in closure   # engine bookkeeping is not hashed


def test08_keys_follow_file_content_not_path_spelling(tmp_path):
    """The same scene reached by another spelling of its path, or a copy of its assets in
    another folder, gets the same keys: input files enter keys by content."""
    import shutil
    a = _keys(load_scene(REPO / "scenes" / "default.toml"))
    b = _keys(load_scene(REPO / "scenes" / ".." / "scenes" / "default.toml"))
    assert a == b
    shutil.copytree(REPO / "scenes", tmp_path / "scenes")
    c = _keys(load_scene(tmp_path / "scenes" / "default.toml"))
    assert c == a
    (tmp_path / "scenes" / "assets" / "lps_head" / "Map-COL.jpg").write_bytes(
        (REPO / "scenes" / "assets" / "lps_head" / "Map-COL.jpg").read_bytes()[:-1] + b"\0")
    d = _keys(load_scene(tmp_path / "scenes" / "default.toml"))
    assert d["mesh_source"] != a["mesh_source"]          # content changed: key changed
