"""Views: close-up cameras beside the main one.  A view validates like the camera, names its
lighting conditions like [render] lights, and every image, reference and difference of one
of its conditions is planned through its camera under the label ``<condition>@<view>``;
camera-independent passes (the BSSRDF's irradiance) are shared with the main camera."""
from __future__ import annotations

import tomllib

import pytest

from dermis.pipeline.config import VIEW_MARK, condition_of, scene_from_dict
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.plan import build_graph
from scene_toml import QUICK, TINY, merge

NOSE = {"name": "nose", "lights": ["point"],
        "camera": {"position": [0.0, -30.0, 330.0], "look_at": [0.0, -30.0, 30.0],
                   "fov_deg": 8.0, "width": 24, "height": 24}}


def scene(views, **over):
    base = merge(tomllib.loads(QUICK.read_text()), merge(TINY, over))
    base["views"] = views
    return scene_from_dict(base, where="s.toml")


def test01_view_conditions_are_labelled_and_see_through_their_camera():
    s = scene([NOSE], render={"models": ["lafortune", "bssrdf"], "lights": ["point", "area"],
                              "geometries": ["high", "low_bump"]})
    labels = [l for l, _ in s.light_groups()]
    assert labels == ["point", "area", f"point{VIEW_MARK}nose"]
    assert [l for l, _ in s.light_groups("nose")] == ["point@nose"]
    assert s.camera_of("point@nose").fov_deg == 8.0 and s.camera_of("point") == s.camera
    assert s.geometries_of("point@nose") == ("high",)   # a close-up renders the scan
    assert condition_of("point@nose") == "point"
    nodes, _ = build_graph(s)
    close = {nid: n for nid, n in nodes.items() if n.params.get("label") == "point@nose"}
    kinds = sorted({n.stage for n in close.values()})
    assert kinds == ["bssrdf", "differences", "render", "visibility"], kinds
    for n in close.values():
        if "camera" in n.params:
            assert n.params["camera"]["width"] == 24 and n.params["camera"]["fov_deg"] == 8.0
    # one irradiance pass per condition and mesh, read by the main camera's and the view's
    irr = [n for n in nodes.values() if n.stage == "irradiance"]
    assert sorted((n.deps["mesh"], n.params["label"]) for n in irr) == [
        ("mesh_high", "area"), ("mesh_high", "point"), ("mesh_low", "area"), ("mesh_low", "point")]
    bss = nodes["render-bssrdf-point@nose-high"]
    assert bss.deps["irradiance"] == nodes["render-bssrdf-point-high"].deps["irradiance"]
    assert not any(n.params.get("geometry") == "low_bump" and VIEW_MARK in n.params["label"]
                   for n in nodes.values())


def test02_views_without_lights_see_the_main_conditions():
    s = scene([{**NOSE, "lights": []}], render={"lights": ["point", "area"]})
    assert [l for l, _ in s.light_groups("nose")] == ["point@nose", "area@nose"]


def test03_reference_of_a_view_uses_its_camera():
    s = scene([NOSE], reference={"enabled": True, "width": 0, "height": 0})
    from dermis.pipeline.registry import stage
    node = stage("reference").node(s, "point@nose", dict(s.light_groups())["point@nose"])
    assert node.params["camera"]["fov_deg"] == 8.0
    assert (node.params["reference"]["width"], node.params["reference"]["height"]) == (24, 24)


@pytest.mark.parametrize("view, key, rule", [
    ({**NOSE, "name": "main"}, "views[0].name", "names the [camera] view"),
    ({**NOSE, "name": "a@b"}, "views[0].name", "must be a plain name"),
    ({**NOSE, "lights": ["nope"]}, "views[0].lights", '"nope" (in "nope") names no [[lights]]'),
    ({**NOSE, "lights": ["point", "point"]}, "views[0].lights", "listed twice"),
    ({**NOSE, "geometries": ["medium"]}, "views[0].geometries", "is not one of"),
    ({**NOSE, "camera": {**NOSE["camera"], "look_at": NOSE["camera"]["position"]}},
     "views[0].camera.look_at", "must differ from views[0].camera.position"),
    ({**NOSE, "camera": {**NOSE["camera"], "width": 0}}, "views[0].camera.width", ">= 1"),
    ({**NOSE, "colour": 1}, "views[0].colour", "unknown key"),
])
def test04_bad_views_are_refused_at_load_naming_the_key(view, key, rule):
    with pytest.raises(ConfigError) as e:
        scene([view])
    assert f"s.toml: {key}" in str(e.value) and rule in str(e.value), str(e.value)


def test05_duplicate_views_and_view_marks_in_light_names_are_refused():
    with pytest.raises(ConfigError, match='views: name "nose" is used twice'):
        scene([NOSE, NOSE])
    base = merge(tomllib.loads(QUICK.read_text()), TINY)
    base["lights"][0]["name"] = "key@1"
    base["render"]["lights"] = ["key@1"]
    with pytest.raises(ConfigError, match=r"lights\[0\].name = \"key@1\": must be a plain name"):
        scene_from_dict(base, where="s.toml")
    base = merge(tomllib.loads(QUICK.read_text()), TINY)
    base["views"] = {"name": "nose"}
    with pytest.raises(ConfigError, match=r"views: must be an array of tables"):
        scene_from_dict(base, where="s.toml")


def test06_a_view_renders_at_its_own_size(tmp_path):
    """End to end: the close-up's image has the view's size and sees the surface."""
    from dermis.pipeline import artifacts
    from dermis.pipeline.api import run
    s = scene([NOSE], output={"previews": False, "output_dir": str(tmp_path / "out")})
    summary = run(s, cache=tmp_path / "cache", export=False)
    got = {n.id: n for n in summary.nodes}
    img = artifacts.load(got["render-lafortune-point@nose-high"].path)
    assert img.linear.shape == (24, 24, 3) and img.mask.mean() > 0.5
    main = artifacts.load(got["render-lafortune-point-high"].path)
    assert main.linear.shape == (32, 32, 3)
