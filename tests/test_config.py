"""Scene files: defaults, unit conversion, and one clear error (exit code 2) per bad input."""
import pytest

from dermis.pipeline.cli import main
from dermis.pipeline.config import default_scene_path, load_scene
from dermis.pipeline.errors import ConfigError

GOOD_LAYER = """
[[optics.layers]]
thickness_mm = 0.25
eta = 1.4
sigma_a = [0.5, 1.0, 2.0]
sigma_s_prime = [2.0, 2.5, 3.0]
"""


def write(tmp_path, text, name="scene.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test01_embedded_default_loads_with_thesis_numbers():
    s = load_scene()
    assert s.path == str(default_scene_path())
    assert s.mesh.source.endswith("assets/lps_head/LeePerrySmith_cm.obj")   # the packaged scan
    assert s.mesh.low_triangles == 16_750 and s.bake.resolution == 4096
    assert (s.camera.width, s.camera.height) == (800, 800)
    assert {l.type for l in s.lights} == {"point", "disc", "directional", "environment"}
    disc = s.light_by_name["area"]
    assert disc.radius == 70.0 and disc.samples == 16
    assert s.optics is not None and len(s.optics.layers) >= 2


def test02_lengths_convert_to_mm(tmp_path):
    p = write(tmp_path, '[scene]\nunits = "cm"\n[camera]\nposition = [0, 5, 90]\n'
                        '[[lights]]\nname = "a"\ntype = "disc"\nradius = 7\n')
    s = load_scene(p)
    assert s.camera.position == (0.0, 50.0, 900.0)
    assert s.lights[0].radius == 70.0


@pytest.mark.parametrize("text, key, rule", [
    ('[mesh]\nhigh_trianglez = 5\n', "mesh.high_trianglez", "did you mean 'high_triangles'"),
    ('[mesh]\nhigh_triangles = "many"\n', "mesh.high_triangles", "must be an integer"),
    ('[camera]\nfov_deg = -3\n', "camera.fov_deg", "must be > 0"),
    ('[mesh]\nsource = "missing_head.obj"\n', "mesh.source", "file not found"),
    ('[render]\nmodels = ["lafortune", "bsdrf"]\n', "render.models", "did you mean 'bssrdf'"),
    ('[[lights]]\nname = "k"\ntype = "spot"\n', "lights[0].type", "must be one of"),
    ('[[lights]]\nname = "k"\ntype = "point"\nintensity = [1, -1, 1]\n', "lights[0].intensity[1]",
     "must be >= 0"),
    (GOOD_LAYER.replace("sigma_a = [0.5, 1.0, 2.0]", "sigma_a = [-0.5, 1.0, 2.0]"),
     "layers[0].sigma_a", "must be >= 0"),
    (GOOD_LAYER + "g = 1.2\n", "layers[0].g", "(-1, 1)"),
    (GOOD_LAYER.replace("eta = 1.4", "eta = 0.8"), "layers[0].eta", "must be >= 1"),
    ('[optics]\npreset = "skin9"\n', "optics.preset", "must be one of"),
    ('[render]\nlights = ["nope"]\n', "render.lights", "names no [[lights]] entry"),
])
def test03_bad_input_exit_code_2_names_key(tmp_path, capsys, text, key, rule):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_scene(p)
    msg = str(info.value)
    assert str(p) in msg and key in msg and rule in msg, msg
    assert main(["status", str(p), "--cache", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dermis: error:") and key in err


def test04_all_problems_reported_at_once(tmp_path):
    p = write(tmp_path, '[mesh]\nseedz = 1\n[camera]\nwidth = 0\n')
    with pytest.raises(ConfigError) as info:
        load_scene(p)
    assert "mesh.seedz" in str(info.value) and "camera.width" in str(info.value)


def test05_missing_scene_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="scene file does not exist"):
        load_scene(tmp_path / "nope.toml")
    p = write(tmp_path, "[mesh\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scene(p)


def test06_duplicate_light_names(tmp_path):
    p = write(tmp_path, '[[lights]]\nname = "k"\ntype = "point"\n[[lights]]\nname = "k"\n'
                        'type = "directional"\n')
    with pytest.raises(ConfigError, match='name "k" is used twice'):
        load_scene(p)


def test_readme_scene_format_table_is_the_schema():
    """README's scene-format reference is generated from the schema's field docs: no drift."""
    from pathlib import Path
    from dermis.pipeline.schema_doc import schema_markdown
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    begin, end = "<!-- scene-format:begin -->\n", "\n<!-- scene-format:end -->"
    assert text[text.index(begin) + len(begin):text.index(end)] == schema_markdown()
