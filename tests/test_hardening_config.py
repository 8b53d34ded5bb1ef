"""Scene validation at load and clean exits: every bad value below ends in exit 2 with one
message naming the file, the dotted key, the value and the rule, never a traceback, and before
any stage runs.

Scenes are the quick scene (scenes/quick.toml) cut to a 2,000-triangle head, one model, one
light, one geometry and 32 x 32 pixels, with the case's settings merged over it; they run
through ``dermis.pipeline.cli.main`` in-process.  The Dask failures (a worker killed every
time it runs a task, Ctrl-C) run against a stand-in client, so they need no cluster.
"""
from __future__ import annotations

import importlib.metadata
import json
import logging
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest

import dermis
from dermis.pipeline import distributed
from dermis.pipeline.cli import main
from dermis.pipeline.config import load_scene
from dermis.pipeline.resources import estimate_memory
from dermis.pipeline.errors import ConfigError, DermisError

sys.path.insert(0, str(Path(__file__).parent))
from scene_toml import scene_file  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
POINT = {"name": "point", "type": "point", "position": [350.0, 450.0, 600.0],
         "intensity": [4.0e5, 4.0e5, 4.0e5]}
LAYER = {"thickness_mm": "inf", "eta": 1.4, "sigma_a": [0.1, 0.1, 0.1],
         "sigma_s_prime": [1.0, 1.0, 1.0]}



def _run(argv, capsys) -> tuple[int, str]:
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return rc, err


# --------------------------------------------------------------------------- refused at load
REFUSED_AT_LOAD = {  # id: (overrides, substrings the message must hold)
    "units_not_a_string": ({"scene": {"units": ["mm"]}},
                           ['scene.units = ["mm"]', "must be a string"]),
    "preset_not_a_string": ({"optics": {"preset": ["two_layer"]}},
                            ['optics.preset = ["two_layer"]', "must be one of"]),
    "camera_position_strings": ({"camera": {"position": ["a", "b", "c"]}},
                                ['camera.position[0] = "a"', "must be a number"]),
    "camera_up_strings": ({"camera": {"up": ["x", "y", "z"]}},
                          ['camera.up[0] = "x"', "must be a number"]),
    "intensity_strings": ({"lights": [dict(POINT, intensity=["a", "b", "c"])]},
                          ['lights[0].intensity[0] = "a"', "must be a number"]),
    "direction_strings": ({"lights": [dict(POINT, type="directional",
                                           direction=["a", "b", "c"])]},
                          ['lights[0].direction[0] = "a"', "must be a number"]),
    "render_lights_not_names": ({"render": {"lights": [1, 2, 3]}},
                                ["render.lights = [1, 2, 3]", "1 is not a string"]),
    "point_density_underflows": ({"bssrdf": {"point_density": 1e-300},
                                  "render": {"models": ["bssrdf"]}},
                                 ["bssrdf.point_density = 1e-300", "must give at least 1",
                                  "point_density >="]),
    "point_light_overflows": ({"lights": [dict(POINT, position=[1e39, 0.0, 0.0])]},
                              ["lights[0].position[0] = 1e+39 (mm)", "at most 1e+18 mm"]),
    "disc_radius_overflows": ({"lights": [dict(POINT, type="disc", radius=1e300,
                                               direction=[0.0, 0.0, 1.0])]},
                              ["lights[0].radius = 1e+300 (mm)", "at most 1e+18 mm"]),
    "point_position_empty": ({"lights": [dict(POINT, position=[])]},
                             ["lights[0].position = []", "must have 3 numbers"]),
    "max_distance_overflows_in_metres": (
        {"scene": {"units": "m"}, "camera": {"position": [0.0, -0.015, 1.0],
                                             "look_at": [0.0, -0.015, 0.0]},
         "lights": [dict(POINT, position=[0.35, 0.45, 0.6])], "bake": {"max_distance": 1e306}},
        ["bake.max_distance = 1e+306 (m)", "is inf mm", "at most 1e+18 mm"]),
    "no_layer_scatters": ({"optics": {"layers": [dict(LAYER, sigma_s_prime=[0.0, 0.0, 0.0])]},
                           "render": {"models": ["bssrdf"]}},
                          ["sigma_s_prime = 0 in every layer", "must scatter"]),
    "hk93_eta_out_of_range": ({"optics": {"layers": [dict(LAYER, eta=100.0)]},
                               "render": {"models": ["hk93"]}},
                              ["optics.layers[0].eta = 100", "must be in [1, 3]", "hk93"]),
    "hk93_three_layers": ({"optics": {"layers": [dict(LAYER, thickness_mm=0.1)] * 2 + [LAYER]},
                           "render": {"models": ["asperity"], "asperity_base": "hk93"}},
                          ["3 layers of non-zero thickness", "hk93 model takes 1 or 2"]),
    "direction_underflows": ({"lights": [dict(POINT, type="directional",
                                              direction=[1e-300, 0.0, 0.0])]},
                             ["lights[0].direction = [1e-300, 0.0, 0.0]", "has length 1e-300",
                              "[1e-150, 1e+150]"]),
    "camera_up_overflows": ({"camera": {"up": [0.0, 1e300, 0.0]}},
                            ["camera.up = [0.0, 1e+300, 0.0]", "has length 1e+300"]),
    "camera_far_in_metres": ({"scene": {"units": "m"}, "camera": {"position": [0.0, 0.0, 1e306],
                                                                 "look_at": [0.0, 0.0, 0.0]},
                              "lights": [dict(POINT, position=[0.35, 0.45, 0.6])]},
                             ["camera.position[2] = 1e+306 (m)", "at most 1e+18 mm"]),
    "reference_size_while_disabled": ({"reference": {"width": 3, "height": 3,
                                                     "enabled": False}},
                                      ["reference.width x height = 3 x 3",
                                       "must divide the camera's 32 x 32"]),
    "reference_lights_while_disabled": ({"reference": {"width": 16, "height": 16,
                                                       "enabled": False, "lights": ["nope"]}},
                                        ['reference.lights: "nope" is not a lighting condition']),
}


@pytest.mark.parametrize("case", sorted(REFUSED_AT_LOAD))
def test01_bad_value_is_refused_at_load_naming_file_key_value_and_rule(case, tmp_path, capsys,
                                                                        monkeypatch):
    monkeypatch.setenv("DERMIS_MEMORY_MB", "65536")   # the memory check is not the subject
    over, expect = REFUSED_AT_LOAD[case]
    scene = scene_file(tmp_path, over)
    cache = tmp_path / "cache"
    rc, err = _run(["run", scene, "--cache", cache, "-q"], capsys)
    assert rc == 2, err
    assert str(scene) in err
    for text in expect:
        assert text in err, (text, err)
    assert "names no [[lights]] entry" not in err     # a refused light is still named
    assert not cache.exists() and not (tmp_path / "out").exists()   # refused before any work


def test02_an_overflowing_camera_blames_its_own_key_not_camera_up(tmp_path, capsys):
    over, _ = REFUSED_AT_LOAD["camera_far_in_metres"]
    rc, err = _run(["run", scene_file(tmp_path, over), "--cache", tmp_path / "c"], capsys)
    assert rc == 2 and "camera.up" not in err, err


@pytest.mark.parametrize("over", [
    {"reference": {"enabled": False}},                       # defaults are not the file's
    {"lights": [dict(POINT, type="directional", direction=[1e-100, 0.0, 0.0])]},
    {"lights": [dict(POINT, position=[1e17, 0.0, 0.0])]},   # far, but within the bound
    {"optics": {"layers": [dict(LAYER, eta=3.5)]}},          # no hk93 rendered: any eta >= 1
    {"optics": {"layers": [dict(LAYER, sigma_s_prime=[0.0, 0.0, 0.0])]},   # no BSSRDF
     "render": {"models": ["lafortune", "hk93"]}},
])
def test03_valid_scenes_near_the_new_rules_still_load(over, tmp_path, monkeypatch):
    monkeypatch.setenv("DERMIS_MEMORY_MB", "65536")
    load_scene(scene_file(tmp_path, over))


def test04_length_and_vector_values_are_the_same_as_before(tmp_path):
    """The validation returns the very numbers the file gives, converted to mm as before."""
    scene = load_scene(scene_file(tmp_path, {"scene": {"units": "cm"},
                                             "camera": {"position": [0, -1.5, 100],
                                                        "look_at": [0.0, -1.5, 0.0]}}))
    assert scene.camera.position == (0.0, -15.0, 1000.0)
    assert scene.lights[0].position == (3500.0, 4500.0, 6000.0)
    assert scene.render.lights == ("point",)


# --------------------------------------------------------------------------- files
def test05_non_utf8_sweep_scene_and_layer_files_exit_2_naming_the_file(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b'[scene]\nname = "caf\xe9"\n')
    for argv in (["sweep", bad, "--cache", tmp_path / "c"], ["run", bad, "-q"], ["profile", bad]):
        rc, err = _run(argv, capsys)
        assert rc == 2, (argv, err)
        assert str(bad) in err and "not a text (UTF-8) file" in err and "0xe9" in err, err
    with pytest.raises(ConfigError, match="not a text"):
        from dermis.optics.layers import load_layers_toml
        load_layers_toml(bad)


# --------------------------------------------------------------------------- report
def test06_report_of_a_scene_without_one_names_the_setting_not_a_flag(tmp_path, capsys):
    rc, err = _run(["report", scene_file(tmp_path), "--cache", tmp_path / "c", "-q"], capsys)
    assert rc == 2
    assert "--until" not in err and 'render.models = ["lafortune"]' in err, err
    assert "makes no report" in err and 'must list "bssrdf"' in err


# --------------------------------------------------------------------------- version
def test07_version_is_the_package_metadata_version(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out.strip()
    assert out == f"dermis {dermis.__version__}"
    assert importlib.metadata.version("dermis") == dermis.__version__


# --------------------------------------------------------------------------- Dask
def test08_unreachable_or_malformed_scheduler_exits_2_quickly(tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed")
    import time
    monkeypatch.setattr(distributed, "CONNECT_TIMEOUT_S", 1)
    scene = tmp_path / "sweep.toml"
    scene.write_text(scene_file(tmp_path, {"render": {"models": ["bssrdf"]}}).read_text()
                     + '[sweep]\n[sweep.knobs]\n"bssrdf.epsilon" = [1.0, 0.5]\n')
    for address, text in (("tcp://127.0.0.1:1", "no Dask scheduler answered within 1 s"),
                          ("not an address", "not a Dask scheduler address")):
        t0 = time.perf_counter()
        rc, err = _run(["sweep", scene, "--cache", tmp_path / "c", "--scheduler", address],
                       capsys)
        assert rc == 2 and f"--scheduler '{address}'" in err and text in err, err
        assert time.perf_counter() - t0 < 20


class _Future:
    def __init__(self, key, fail):
        self.key, self.fail = key, fail

    def result(self):
        raise self.fail


class _Client:
    """Stands in for dask.distributed.Client: every task fails with ``fail``."""

    closed = False
    log_level_at_close = None

    def __init__(self, address, timeout=None):
        self.address = address

    def submit(self, fn, *args, key, **kw):
        return _Future(key, _Client.fail)

    def close(self):
        _Client.closed = True
        _Client.log_level_at_close = logging.getLogger("distributed").getEffectiveLevel()


@pytest.fixture
def stand_in_dask(monkeypatch):
    dd = pytest.importorskip("dask.distributed")
    monkeypatch.setattr(dd, "Client", _Client)
    monkeypatch.setattr(dd, "as_completed", lambda futures: iter(futures))
    monkeypatch.setattr(_Client, "closed", False)
    monkeypatch.setattr(_Client, "log_level_at_close", None)
    level = logging.getLogger("distributed").level
    yield
    assert logging.getLogger("distributed").level == level    # restored after the close


def _toy_graphs():
    from dermis.pipeline.graph import Node
    nodes = {"a": Node("a", "a", "dermis.pipeline.errors", {}, fn=lambda inputs, ctx: None)}
    return [(nodes, ["a"])]


def test09_a_task_whose_worker_dies_every_time_is_reported_not_traced(stand_in_dask, tmp_path):
    from distributed.scheduler import KilledWorker
    _Client.fail = KilledWorker("a-0123abcd", SimpleNamespace(address="tcp://10.0.0.2:4000"), 3)
    with pytest.raises(DermisError) as exc:
        distributed.run_graphs(_toy_graphs(), tmp_path, scheduler="tcp://x:1")
    msg = str(exc.value)
    assert "node a:" in msg and "died 4 times" in msg and "tcp://10.0.0.2:4000" in msg, msg
    assert _Client.closed and _Client.log_level_at_close > logging.CRITICAL


def test10_ctrl_c_during_a_dask_run_closes_the_client_and_leaves_one_message(
        stand_in_dask, tmp_path, capsys, monkeypatch):
    from dermis.reports import sweep
    _Client.fail = KeyboardInterrupt()
    with pytest.raises(KeyboardInterrupt):
        distributed.run_graphs(_toy_graphs(), tmp_path, scheduler="tcp://x:1")
    # closing a cluster whose tasks were cancelled logs their tracebacks: silenced meanwhile
    assert _Client.closed and _Client.log_level_at_close > logging.CRITICAL
    # and through the CLI: exit 130, the one line
    monkeypatch.setattr(sweep, "run_sweep", lambda *a, **k: distributed.run_graphs(
        _toy_graphs(), tmp_path, scheduler="tcp://x:1"))
    scene = scene_file(tmp_path)
    rc, err = _run(["sweep", scene, "--cache", tmp_path / "c", "--scheduler", "tcp://x:1"],
                   capsys)
    assert rc == 130 and err.strip().splitlines() == [
        "dermis: interrupted; finished stages stay cached, the unfinished one was discarded"]


def test11_local_workers_leave_ctrl_c_to_the_submitting_process():
    import signal
    prev = signal.getsignal(signal.SIGINT)
    try:
        distributed.dask_setup(None)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, prev)
        logging.getLogger("distributed.worker.state_machine").setLevel(logging.NOTSET)


# --------------------------------------------------------------------------- memory
MEASURE = textwrap.dedent("""
    import json, resource, sys
    from dermis.pipeline import api
    from dermis.pipeline.config import load_scene
    scene = load_scene(sys.argv[1])
    api.run(scene, cache=sys.argv[2], force=("visibility", "render", "irradiance", "bssrdf",
                                             "images"))
    print(json.dumps(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024))
""")


@pytest.mark.skipif(sys.platform != "linux", reason="ru_maxrss is in KiB on Linux")
def test12_memory_estimate_bounds_the_measured_peak(tmp_path):
    """The render of a small image under the two costliest lights (the environment map with the
    BSSRDF, a disc) peaks below the load-time estimate; the peak is the resident set of a fresh
    process that renders with the meshes, points and profiles already cached."""
    from dermis.pipeline import api
    over = {"camera": {"width": 96, "height": 96},
            "render": {"models": ["lafortune", "bssrdf"], "lights": ["area", "sunset"]}}
    path = scene_file(tmp_path, over)
    scene = load_scene(path)
    cache = tmp_path / "cache"
    for until in ("mesh_high", "samples", "profiles"):
        api.run(scene, cache=cache, until=until, export=False)
    out = subprocess.run([sys.executable, "-c", MEASURE, str(path), str(cache)],
                         capture_output=True, text=True, env=os.environ.copy(), check=True)
    peak = json.loads(out.stdout.strip().splitlines()[-1])
    estimate = max(b for _, _, b in estimate_memory(scene))
    assert peak <= estimate, (peak / 2**20, estimate / 2**20)
    assert estimate < 4 * peak       # an upper bound, not a refusal of every scene
    assert math.isfinite(estimate)
