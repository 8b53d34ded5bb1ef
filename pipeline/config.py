"""Scene files: TOML -> validated, typed dataclasses with defaults.

Every field is declared once, with its type, default, allowed range and unit, in the
dataclasses of :mod:`dermis.pipeline.schema` (re-exported here); one generic walker (:func:`_build`) validates a TOML
table against them.  Errors name the file, the dotted key, the bad value and
what is allowed; unknown keys are errors with a did-you-mean, and all problems
found in one file are reported together.

Lengths: fields marked ``unit="length"`` are written in the scene's
``[scene] units`` (mm by default, or cm / m) and converted to mm at load.
"""
from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import MISSING, fields, is_dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any, get_type_hints

from .errors import ConfigError
from . import registry
from .registry import model
from .model_choice import AUTO, choice_problems, choose, condition_kind
# the schema's names are config's too (callers import both from here)
from .schema import (GEOMETRIES, LENGTH_UNITS, LIGHT_TYPES, MAIN_VIEW, SCHEMA_TABLES,
                     VIEW_MARK, BakeConfig, BssrdfConfig, CameraConfig, CausesConfig, CyclesConfig,
                     LightConfig, MeshConfig, OutputConfig, ReferenceConfig, RenderConfig,
                     ReportConfig, Scene, SceneInfo, ViewConfig, choices_of, condition_of,
                     resolve_path, spec, view_name_of)
from .scene_rules import (check_camera, check_environment_file, check_reference,
                          direction_problem, fmt, plain_name_problem)

__all__ = ["load_scene", "scene_from_dict", "default_scene_path", "condition_problems",
           "LENGTH_UNITS", "GEOMETRIES", "LIGHT_TYPES", "MAIN_VIEW", "SCHEMA_TABLES", "VIEW_MARK",
           "BakeConfig", "BssrdfConfig", "CameraConfig", "CausesConfig", "CyclesConfig",
           "LightConfig",
           "MeshConfig", "OutputConfig", "ReferenceConfig", "RenderConfig", "ReportConfig",
           "Scene", "SceneInfo", "ViewConfig", "choices_of", "condition_of", "view_name_of",
           "resolve_path",
           "spec"]

# --------------------------------------------------------------------------- validation
class _Problems(list):
    def add(self, where: str, key: str, msg: str):
        self.append(f"{where}: {key}{msg}")


def _did_you_mean(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


# Largest coordinate or size, in mm, after the unit conversion.  The renderer squares
# distances between points in float32 (a light sample's |q - p|^2, lighting/emitters.py),
# which overflows (3.4e38) beyond |q - p| ~ 1.8e19 mm; two points within 1e18 mm of the
# origin are at most 2 sqrt(3) 1e18 mm apart, 1.2e37 squared (a light-year is 9.5e18 mm).
MAX_LENGTH_MM = 1e18
UNIT_NAMES = {scale: name for name, scale in LENGTH_UNITS.items()}


def _check_number(value, meta, where, key, problems, *, integer: bool, scale: float) -> Any:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (
            integer and not isinstance(value, int)):
        kind = "an integer" if integer else "a number"
        problems.add(where, key, f" = {fmt(value)}: must be {kind}")
        return None
    if not math.isfinite(value):
        problems.add(where, key, f" = {fmt(value)}: must be finite")
        return None
    lo, hi = meta.get("lo"), meta.get("hi")
    length = meta.get("unit") == "length"
    unit = f" ({UNIT_NAMES.get(scale, 'mm')})" if length else ""
    if lo is not None and (value < lo or (meta.get("lo_open") and value == lo)):
        rel = ">" if meta.get("lo_open") else ">="
        problems.add(where, key, f" = {fmt(value)}{unit}: must be {rel} {lo}")
        return None
    if hi is not None and (value > hi or (meta.get("hi_open") and value == hi)):
        rel = "<" if meta.get("hi_open") else "<="
        problems.add(where, key, f" = {fmt(value)}{unit}: must be {rel} {hi}")
        return None
    out = value * scale if scale != 1.0 else value
    if length and not abs(out) <= MAX_LENGTH_MM:
        problems.add(where, key, f" = {fmt(value)}{unit}: is {float(out):g} mm; a length "
                     f"must be at most {MAX_LENGTH_MM:g} mm in magnitude (the renderer squares "
                     "distances in single precision, which overflows beyond)")
        return None
    return out


def _check_value(value, tp, meta, where, key, problems, length_scale):
    scale = length_scale if meta.get("unit") == "length" else 1.0
    choices = choices_of(meta)
    if tp is bool:
        if not isinstance(value, bool):
            problems.add(where, key, f" = {fmt(value)}: must be true or false")
            return None
        return value
    if tp is int or tp is float:
        return _check_number(value, meta, where, key, problems, integer=tp is int, scale=scale)
    if tp is str:
        if not isinstance(value, str):
            problems.add(where, key, f" = {fmt(value)}: must be a string")
            return None
        if choices and value not in choices:
            problems.add(where, key, f" = {fmt(value)}: must be one of "
                         + ", ".join(fmt(c) for c in choices) + _did_you_mean(value, choices))
            return None
        return value
    if tp is tuple:  # vectors of 3 numbers, or lists of choices / names
        if not isinstance(value, list):
            problems.add(where, key, f" = {fmt(value)}: must be an array")
            return None
        if choices:
            bad = [v for v in value if v not in choices]
            if bad:
                problems.add(where, key, f" = {fmt(value)}: {fmt(bad[0])} is not one of "
                             + ", ".join(fmt(c) for c in choices)
                             + _did_you_mean(str(bad[0]), choices))
                return None
            return tuple(value)
        if meta.get("names"):
            bad = [v for v in value if not isinstance(v, str)]
            if bad:
                problems.add(where, key, f" = {fmt(value)}: {fmt(bad[0])} is not a string; "
                             "must be an array of names (strings)")
                return None
            return tuple(value)
        if len(value) != 3:
            problems.add(where, key, f" = {fmt(value)}: must have 3 numbers")
            return None
        out = [_check_number(v, meta, where, f"{key}[{i}]", problems, integer=False, scale=scale)
               for i, v in enumerate(value)]
        return None if any(v is None for v in out) else tuple(float(v) for v in out)
    return value


def _build(cls, table, where: str, prefix: str, problems: _Problems, length_scale: float):
    """Validate ``table`` against dataclass ``cls``; collect problems, return instance or None."""
    if not isinstance(table, dict):
        problems.add(where, prefix.rstrip("."), f" = {fmt(table)}: must be a table")
        return None
    hints = get_type_hints(cls)
    known = {f.name: f for f in fields(cls) if f.name != "path"
             and not f.metadata.get("internal")}
    for key in table:
        if key not in known:
            problems.add(where, prefix + key, ": unknown key" + _did_you_mean(key, known)
                         + f"; allowed: {', '.join(known)}")
    values = {}
    for name, f in known.items():
        key = prefix + name
        if name not in table:
            if f.default is MISSING and f.default_factory is MISSING:
                problems.add(where, key, ": required key is missing")
            continue
        tp = hints[name]
        if is_dataclass(tp):
            values[name] = _build(tp, table[name], where, key + ".", problems, length_scale)
        else:
            values[name] = _check_value(table[name], tp, f.metadata, where, key, problems,
                                        length_scale)
    if any(v is None for k, v in values.items() if k in table):
        return None
    try:
        return cls(**values)
    except TypeError:
        return None


def default_scene_path() -> Path:
    """The embedded default scene (the packaged Lee Perry-Smith scan), shipped in the package."""
    return Path(str(resources.files("dermis.scenes"))) / "default.toml"


def load_scene(path: str | Path | None = None, *, overrides: dict | None = None) -> Scene:
    """Load and validate a scene file.

    Parameters
    ----------
    path : str or Path, optional
        TOML scene file; None loads the embedded default (:func:`default_scene_path`).
    overrides : dict, optional
        Nested dict merged over the file's tables before validation (API/tests).

    Raises
    ------
    ConfigError
        On any problem; the message lists every problem with file, key, value and rule.
    """
    path = Path(path) if path is not None else default_scene_path()
    where = str(path)
    if not path.is_file():
        raise ConfigError(f"{where}: scene file does not exist")
    try:
        table = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{where}: not a text (UTF-8) file") from None
    return scene_from_dict(table, where=where, overrides=overrides)


def _sections(body: dict, where: str, length_scale: float):
    """The scene's tables that validate on their own (None for the others): the cross-field
    checks then still run when some other table has a problem (all problems listed at once)."""
    from types import SimpleNamespace
    hints = get_type_hints(Scene)
    out = {}
    for f in fields(Scene):
        if not is_dataclass(hints.get(f.name)):
            continue
        cls, table = hints[f.name], body.get(f.name, {})
        if isinstance(table, dict):  # keep the keys that validate on their own (others: default)
            table = {k: v for k, v in table.items() if _build(
                cls, {k: v}, where, f.name + ".", _Problems(), length_scale) is not None}
        out[f.name] = _build(cls, table, where, f.name + ".", _Problems(), length_scale)
    return SimpleNamespace(**out)


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def condition_problems(labels, named, key: str, where: str) -> list[str]:
    """The problems of lighting conditions ``labels`` (names of ``named`` lights, "a+b"
    lights together) given at ``key``."""
    problems = _Problems()
    for label in labels:
        parts = label.split("+")
        for n in parts:
            if n not in named:
                problems.add(where, key, f": {fmt(n)} (in {fmt(label)}) names no [[lights]] "
                             "entry; defined: " + (", ".join(fmt(x) for x in named) or "none"))
        for n in sorted({n for n in parts if parts.count(n) > 1}):
            problems.add(where, key, f": {fmt(label)} names light {fmt(n)} {parts.count(n)} "
                         "times; each light may appear once in a lighting condition (raise its "
                         "intensity to brighten it)")
    return list(problems)


def _views(raw, named, where: str, problems: _Problems, length_scale: float) -> tuple:
    """The ``[[views]]`` tables, validated (problems added to ``problems``)."""
    if not isinstance(raw, list):
        problems.add(where, "views", ": must be an array of tables ([[views]])")
        return ()
    views = []
    for i, table in enumerate(raw):
        view = _build(ViewConfig, table, where, f"views[{i}].", problems, length_scale)
        if view is None:
            continue
        why = plain_name_problem(view.name, extra="+" + VIEW_MARK)
        if why or view.name == MAIN_VIEW:
            problems.add(where, f"views[{i}].name", f" = {fmt(view.name)}: "
                         + (why or "names the [camera] view") + " (a view's name becomes part "
                         "of output file names and of its lighting labels, <condition>@<view>)")
        problems += check_camera(view.camera, where, f"views[{i}].camera")
        problems += condition_problems(view.lights, named, f"views[{i}].lights", where)
        for key in ("lights", "geometries"):
            values = getattr(view, key)
            for v in sorted({v for v in values if values.count(v) > 1}):
                problems.add(where, f"views[{i}].{key}", f": {fmt(v)} is listed twice; list "
                             "each once")
        views.append(view)
    names = [v.name for v in views]
    for n in sorted({n for n in names if names.count(n) > 1}):
        problems.add(where, "views", f": name {fmt(n)} is used twice; names must be unique")
    return tuple(views)


def _auto_models(render, report, lights, views, where: str) -> tuple:
    """(label, model) for every lighting condition of ``render.models = ["auto"]``."""
    types = {l.name: l.type for l in lights}
    main = render.lights or tuple(types)
    labels = [(c, False) for c in main] + [(f"{c}{VIEW_MARK}{v.name}", True) for v in views
                                           for c in v.lights or main]
    accuracy = report.accuracy if report is not None else ReportConfig().accuracy
    return tuple((label, choose(condition_kind([types[n] for n in condition_of(label).split("+")
                                                if n in types], close), accuracy,
                                registry.model_names(), where))
                 for label, close in labels)


def scene_from_dict(table: dict, *, where: str = "<scene>", overrides: dict | None = None) -> Scene:
    """Validate an already-parsed scene table (see :func:`load_scene`)."""
    layers = registry.section("optics")      # the layer optics own their validation
    parse_layer_stack, PRESETS = layers.parse_layer_stack, layers.PRESETS
    split_profile_options, with_profile = layers.split_profile_options, layers.with_profile

    if overrides:
        table = _merge(table, overrides)
    problems = _Problems()
    units = table.get("scene", {}).get("units", "mm") if isinstance(table.get("scene"), dict) else "mm"
    length_scale = LENGTH_UNITS.get(units, 1.0) if isinstance(units, str) else 1.0  # else: refused
    body = {k: v for k, v in table.items() if k not in ("lights", "views", "optics", "sweep")}
    if "sweep" in table and not isinstance(table["sweep"], dict):  # checked by `dermis sweep`
        problems.add(where, "sweep", f" = {fmt(table['sweep'])}: must be a table ([sweep])")
    scene = _build(Scene, body, where, "", problems, length_scale)

    lights, light_index = [], []
    raw_lights = table.get("lights", [])
    if not isinstance(raw_lights, list):
        problems.add(where, "lights", ": must be an array of tables ([[lights]])")
        raw_lights = []
    for i, lt in enumerate(raw_lights):
        light = _build(LightConfig, lt, where, f"lights[{i}].", problems, length_scale)
        if light is not None:
            lights.append(light)
            light_index.append(i)
    for k, light in enumerate(lights):  # map paths are relative to the scene file
        i = light_index[k]
        why = plain_name_problem(light.name, extra="+" + VIEW_MARK)
        if why:
            problems.add(where, f"lights[{i}].name", f" = {fmt(light.name)}: {why} (light "
                         "names become parts of output file names; '+' joins lights in "
                         "render.lights, '@' a condition and its view)")
        why = direction_problem(light.direction)
        if light.type in ("directional", "disc") and why:
            problems.add(where, f"lights[{i}].direction", f" = {fmt(light.direction)}: {why} "
                         f"(the {light.type} light's "
                         + ("direction towards the light)" if light.type == "directional"
                            else "disc normal)"))
        if light.type == "environment" and light.map != "procedural_sunset":
            p = resolve_path(light.map, where)
            if not p.is_file():
                problems.add(where, f"lights[{i}].map", f" = {fmt(light.map)}: file not found "
                             f'({p}); use "procedural_sunset" for the embedded sky')
            else:
                problems += check_environment_file(p, where, f"lights[{i}].map", light.map)
            lights[k] = replace(light, map=str(p.resolve()))
    names = [l.name for l in lights]
    # lights refused above keep their names for render.lights (one problem, not two)
    named = names + [lt["name"] for lt in raw_lights if isinstance(lt, dict)
                     and isinstance(lt.get("name"), str) and lt["name"] not in names]
    for n in {n for n in names if names.count(n) > 1}:
        problems.add(where, "lights", f": name {fmt(n)} is used twice; names must be unique")

    optics = table.get("optics", {"preset": "two_layer"})
    stack = None
    profile = {}
    if isinstance(optics, dict):  # profile / photons / seed: the BSSRDF's profile model
        optics, profile, bad = split_profile_options(optics, where=f"{where}: optics")
        problems.extend(bad)
    if not isinstance(optics, dict):
        problems.add(where, "optics", f" = {fmt(optics)}: must be a table")
    elif "preset" in optics:
        extra = set(optics) - {"preset"}
        if extra:
            problems.add(where, "optics", f": preset and {sorted(extra)} conflict; give either "
                         "preset or an explicit [[optics.layers]] stack")
        elif not isinstance(optics["preset"], str) or optics["preset"] not in PRESETS:
            problems.add(where, "optics.preset", f" = {fmt(optics['preset'])}: must be one of "
                         + ", ".join(fmt(p) for p in PRESETS)
                         + _did_you_mean(str(optics["preset"]), PRESETS))
        else:
            stack = PRESETS[optics["preset"]]
    else:
        try:
            stack = parse_layer_stack(optics, where=f"{where}: optics")
        except ConfigError as exc:
            problems.append(str(exc))
    if stack is not None:
        stack = with_profile(stack, **profile)

    # cross-field checks run on every table that validated, even when another did not
    sc = scene if scene is not None else _sections(body, where, length_scale)
    why = plain_name_problem(sc.scene.name) if sc.scene is not None else None
    if why:
        problems.add(where, "scene.name", f" = {fmt(sc.scene.name)}: {why} (outputs go "
                     "to output_dir/<scene.name>/)")
    render = sc.render
    if render is not None:
        problems += condition_problems(render.lights, named, "render.lights", where)
        for key in ("lights", "models", "geometries"):
            values = getattr(render, key)
            for v in sorted({v for v in values if values.count(v) > 1}):
                problems.add(where, f"render.{key}", f": {fmt(v)} is listed twice; list each "
                             "once")
        if render.models and not raw_lights:
            problems.add(where, "lights", f": no [[lights]] defined, but render.models = "
                         f"{fmt(list(render.models))} need at least one light (or set "
                         "render.models = [] to prepare the meshes only)")
    if sc.camera is not None:
        problems += check_camera(sc.camera, where)
    views = _views(table.get("views", []), named, where, problems, length_scale)
    chosen = ()
    if render is not None and render.models == (AUTO,):
        chosen = _auto_models(render, sc.report, lights, views, where)
        render = replace(render, models=tuple(m for m in registry.model_names()
                                              if m in {c for _, c in chosen}))
        if scene is not None:
            scene = replace(scene, render=render)
    elif render is not None:
        problems += choice_problems(render.models, where)
    if render is not None and stack is not None:   # what each rendered model needs
        for name in (m for m in render.models if m != AUTO):   # "auto" alone: refused above
            check = model(name).check
            found = check(stack, dict(vars(sc)), where) if check is not None else []
            problems += [p for p in found if p not in problems]   # bssrdf_mc shares bssrdf's
    given = table.get("reference")
    if sc.reference is not None and isinstance(given, dict):
        labels = (render.lights or tuple(names)) if render is not None else None
        if labels is not None:
            labels = tuple(labels) + tuple(f"{c}{VIEW_MARK}{v.name}" for v in views
                                           for c in v.lights or labels)
        problems += check_reference(sc.reference, set(given), sc.camera, labels, where)
    if sc.mesh is not None:
        if sc.mesh.source != "procedural":
            p = resolve_path(sc.mesh.source, where)
            if not p.is_file():
                problems.add(where, "mesh.source", f" = {fmt(sc.mesh.source)}: file not found "
                             f"({p}); use \"procedural\" for the embedded head")
        for key in ("texture", "displacement"):
            val = getattr(sc.mesh, key)
            if val and not resolve_path(val, where).is_file():
                problems.add(where, f"mesh.{key}", f" = {fmt(val)}: file not found "
                             f"({resolve_path(val, where)})")
        if sc.mesh.low_triangles >= sc.mesh.high_triangles:
            problems.add(where, "mesh.low_triangles", f" = {sc.mesh.low_triangles}: must be "
                         f"< mesh.high_triangles ({sc.mesh.high_triangles})")
    if problems:
        raise ConfigError("\n".join(problems))
    out = Scene(**{**{f.name: getattr(scene, f.name) for f in fields(Scene)},
                   "lights": tuple(lights), "views": views, "optics": stack, "path": where,
                   "chosen": chosen})
    from .resources import resource_problems   # resources reads this module's vocabulary
    problems += [f"{where}: {p}" for p in resource_problems(out)]
    if problems:
        raise ConfigError("\n".join(problems))
    return out
