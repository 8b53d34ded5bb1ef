"""Scene dicts written as TOML files for the tests that feed dermis hostile or edited scenes
(tests/test_hardening*.py): TOML has no writer in the standard library, and a scene uses only
tables, arrays of tables, scalars and arrays."""
from __future__ import annotations

import copy
import json
import re
import tomllib
from pathlib import Path

QUICK = Path(__file__).resolve().parents[1] / "scenes" / "quick.toml"
# The quick scene cut to what a hardening test needs: one small mesh, one light, one model,
# a 32-pixel camera, no previews (a run takes seconds)
TINY = {"mesh": {"high_triangles": 2000, "low_triangles": 400, "procedural_texture_size": 64,
                 "procedural_detail": False},
        "camera": {"width": 32, "height": 32},
        "render": {"models": ["lafortune"], "lights": ["point"], "geometries": ["high"]},
        "output": {"previews": False}}


def toml_value(x) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, str):
        return json.dumps(x)
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in x) + "]"
    return repr(x)


def to_toml(d: dict) -> str:
    """A scene dict as TOML (tables, arrays of tables such as [[lights]] and
    [[optics.layers]], scalars and arrays)."""
    tables = lambda v: isinstance(v, list) and v and isinstance(v[0], dict)  # noqa: E731
    out = [f"{k} = {toml_value(v)}" for k, v in d.items()
           if not isinstance(v, dict) and not tables(v)]
    for k, v in d.items():
        if isinstance(v, dict):
            out.append(f"[{k}]")
            out += [f"{a} = {toml_value(b)}" for a, b in v.items() if not tables(b)]
            for a, b in v.items():
                if tables(b):
                    for item in b:
                        out.append(f"[[{k}.{a}]]")
                        out += [f"{x} = {toml_value(y)}" for x, y in item.items()]
        elif tables(v):
            for item in v:
                out.append(f"[[{k}]]")
                out += [f"{a} = {toml_value(b)}" for a, b in item.items()]
    return "\n".join(out) + "\n"


def merge(a: dict, b: dict) -> dict:
    """``a`` with ``b`` merged in, table by table (a copy)."""
    a = copy.deepcopy(a)
    for k, v in b.items():
        a[k] = merge(a[k], v) if isinstance(v, dict) and isinstance(a.get(k), dict) else v
    return a


def scene_file(folder: Path, over: dict | None = None, name: str = "scene.toml") -> Path:
    """The quick scene with the TINY overrides and ``over`` (an explicit optics stack replaces
    the preset), outputs under ``folder/out`` unless ``over`` names an output folder."""
    d = merge(merge(tomllib.loads(QUICK.read_text()), TINY), over or {})
    if "layers" in (over or {}).get("optics", {}):
        d["optics"] = over["optics"]
    if "output_dir" not in (over or {}).get("output", {}):
        d["output"]["output_dir"] = str(folder / "out")
    path = folder / name
    path.write_text(to_toml(d))
    return path


def quick_with_sweep(folder: Path, *, model: str, lights: str, sweep: str) -> Path:
    """The quick scene's text cut to one ``model`` image per light of ``lights`` (a TOML
    array) on the high mesh, no previews, its outputs in ``folder``, with ``sweep`` (a
    [sweep] table) appended: folder/sweep.toml.  Edited as text, so the file keeps the quick
    scene's comments and layout."""
    src = QUICK.read_text()
    for a, b in ((r"^models = .*$", f'models = ["{model}"]'),
                 (r"^lights = .*$", f"lights = {lights}"),
                 (r"^geometries = .*$", 'geometries = ["high"]'),
                 (r"^previews = true$", "previews = false"),
                 (r'^output_dir = "out"$', f'output_dir = "{folder / "out"}"')):
        src, n = re.subn(a, b, src, count=1, flags=re.M)
        assert n == 1, a
    path = folder / "sweep.toml"
    path.write_text(src + "\n" + sweep)
    return path
