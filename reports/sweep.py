"""``dermis sweep SCENE``: measure the speed-accuracy trade of the knobs a user turns.

A ``[sweep]`` table in the scene names knobs and their values::

    [sweep]
    mode = "one_at_a_time"            # or "grid"
    targets = [0.01, 0.05]            # relative-RMSE targets for the recommendations
    budget_s = 60.0                   # time budget for the third recommendation
    [sweep.knobs]
    "bssrdf.epsilon" = [1.0, 0.5, 0.2]
    "lights.samples" = { range = [4, 64], num = 5, scale = "log" }

Every point is an ordinary scene variant, so the cache reuses everything upstream of the knob,
and all points run as independent node tasks (:mod:`dermis.pipeline.distributed`; ``--workers``,
``--scheduler``).  Each point is timed from the stage metadata (the seconds of the nodes the
knob changed, and of those it shares with the scene as written) and scored against a reference
suited to its knob (:data:`KNOBS`): relative RMSE in linear radiance and FLIP (Andersson et
al. 2020, ``flip-evaluator``) over every image of the scene.  Results: ``sweep.json`` (points,
Pareto fronts, recommended settings), one error-vs-time plot per knob and a joint one, and
``sweep.pdf``.
"""
from __future__ import annotations

import argparse
import copy
import itertools
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dermis.pipeline.config import scene_from_dict
from dermis.pipeline.errors import ConfigError, DermisError
from dermis.pipeline.graph import key_parts, node_key, plan_order
from dermis.pipeline.plan import build_graph
from dermis.reports.sweep_plots import plots
from dermis.reports.sweep_verify import (candidates, choose, config_id, extrapolate,
                                         repeat_seconds, spread)

__all__ = ["KNOBS", "Knob", "SweepSpec", "parse_sweep", "run_sweep", "pareto_front",
           "recommend", "idle_knobs", "add_parser", "run"]


@dataclass(frozen=True)
class Knob:
    """A sweepable setting: where it lives in the scene, which way is finer, its reference.

    reference: "finest" (the sweep's most refined value), "brute_force" (the exact gather),
    "high_mesh" (the same images on the ~1M-triangle mesh) or "monte_carlo" (the same images
    with the Monte Carlo profile table, ``[optics] profile = "monte_carlo"``).
    choices: a categorical knob's values, coarse to fine (``finer = "choices"``).
    also: settings a point of this knob needs besides its value (path -> value).
    order: convergence order p of the error in the knob's step h (``|I(h) - I(0)| ~ h^p``,
    h = 1/value or value) assumed for the extrapolation to the converged answer when the
    three finest values fit no order (reports/sweep_verify.py): 0.5 for sample counts
    (Monte Carlo noise, independent between values, falls as N^-1/2), 1 otherwise (a
    first-order discretisation, the slowest a consistent one converges).
    """

    path: str
    finer: str                 # "higher", "lower" or "choices"
    reference: str = "finest"
    integer: bool = False
    doc: str = ""
    choices: tuple = ()
    also: tuple = ()           # ((path, value), ...)
    order: float = 1.0

    def rank(self, value) -> float:
        """Larger = more refined."""
        if self.choices:
            return float(self.choices.index(value))
        return float(value) if self.finer == "higher" else -float(value)


KNOBS = {k.path: k for k in (
    Knob("bssrdf.epsilon", "lower", "brute_force", doc="gather solid-angle criterion"),
    Knob("bssrdf.point_density", "higher", doc="irradiance points per pi mfp^2"),
    Knob("bssrdf.irradiance_samples", "higher", integer=True, order=0.5,
         doc="irradiance shadow samples"),
    Knob("bssrdf.leaf_size", "lower", "brute_force", integer=True, doc="points per octree leaf"),
    Knob("lights.samples", "higher", integer=True, order=0.5, doc="area/environment light samples"),
    Knob("render.spp", "higher", integer=True, order=0.5, doc="camera samples per pixel (anti-aliasing)"),
    Knob("bake.resolution", "higher", integer=True, doc="baked map resolution"),
    Knob("mesh.low_triangles", "higher", "high_mesh", integer=True,
         doc="triangles of the simplified mesh"),
    # the profile model the BSSRDF renders with (docs/profiles.md); the reference for the
    # profile knobs is the Monte Carlo profile.  The multipole's pole count and FFT grid
    # are not scene settings (stages/profiles.py node: model, photons, seed only), so not knobs.
    Knob("optics.profile", "choices", "monte_carlo", choices=("multipole", "monte_carlo"),
         doc="profile model of the BSSRDF (reference: the Monte Carlo table)"),
    Knob("optics.photons", "higher", integer=True, order=0.5, also=(("optics.profile", "monte_carlo"),),
         doc="photons per channel of the Monte Carlo profile (sets profile = monte_carlo)"),
    Knob("cycles.target_noise", "lower", doc="noise the Cycles models render to (docs/cycles.md)"),
)}

MODES = ("one_at_a_time", "grid")
# Imported by every worker before it times a node: their first import is a per-process cost.
WARM_IMPORTS = ("numpy", "scipy.fft", "scipy.sparse", "scipy.spatial", "open3d", "igl",
                "pyopencl", "OpenImageIO", "dermis.lighting.visibility")


@dataclass
class SweepSpec:
    knobs: dict                # path -> list of values
    mode: str = "one_at_a_time"
    targets: tuple = (0.01, 0.05)
    budget_s: float | None = None
    repeats: int = 3           # timing samples per point (median, min-max spread)
    tries: int = 3             # candidates rendered per recommendation before giving up


def _problem(where: str, key: str, msg: str) -> str:
    return f"{where}: sweep.{key}{msg}"


def _values(where: str, name: str, spec, knob: Knob) -> list:
    if knob.choices:
        if not isinstance(spec, list) or not spec:
            raise ConfigError(_problem(where, f"knobs.{name}", f" = {spec!r}: must be a "
                                       "non-empty list of " + ", ".join(map(repr, knob.choices))))
        for v in spec:
            if v not in knob.choices:
                raise ConfigError(_problem(where, f"knobs.{name}", f": value {v!r} must be one "
                                           "of " + ", ".join(map(repr, knob.choices))))
        return sorted(set(spec), key=spec.index)
    if isinstance(spec, list):
        values = spec
    elif isinstance(spec, dict):
        extra = set(spec) - {"range", "num", "scale"}
        if extra:
            raise ConfigError(_problem(where, f"knobs.{name}", f": unknown keys {sorted(extra)}; "
                                       "allowed: range, num, scale"))
        rng, num, scale = spec.get("range"), spec.get("num", 5), spec.get("scale", "linear")
        if (not isinstance(rng, list) or len(rng) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rng)):
            raise ConfigError(_problem(where, f"knobs.{name}.range", f" = {rng!r}: must be "
                                       "[low, high] numbers"))
        if not isinstance(num, int) or isinstance(num, bool) or num < 2:
            raise ConfigError(_problem(where, f"knobs.{name}.num", f" = {num!r}: must be an "
                                       "integer >= 2"))
        if scale not in ("linear", "log"):
            raise ConfigError(_problem(where, f"knobs.{name}.scale", f" = {scale!r}: must be "
                                       '"linear" or "log"'))
        lo, hi = float(rng[0]), float(rng[1])
        if scale == "log" and not (lo > 0 and hi > 0):
            raise ConfigError(_problem(where, f"knobs.{name}.range", f" = {rng!r}: a log range "
                                       "needs positive ends"))
        values = list(np.geomspace(lo, hi, num) if scale == "log" else np.linspace(lo, hi, num))
    else:
        raise ConfigError(_problem(where, f"knobs.{name}", f" = {spec!r}: must be a list of "
                                   "values or {range = [lo, hi], num = N, scale = ...}"))
    if not values:
        raise ConfigError(_problem(where, f"knobs.{name}", " = []: needs at least one value"))
    out = []
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(_problem(where, f"knobs.{name}", f": value {v!r} must be a "
                                       "finite number"))
        out.append(int(round(v)) if knob.integer else float(v))
    return sorted(set(out), key=out.index)


def parse_sweep(table, where: str) -> SweepSpec:
    """Validate a ``[sweep]`` table; errors name the file, the key, the value and the rule."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: sweep = {table!r}: must be a table ([sweep])")
    extra = set(table) - {"knobs", "mode", "targets", "budget_s", "repeats", "tries"}
    if extra:
        raise ConfigError(f"{where}: sweep: unknown keys {sorted(extra)}; allowed: knobs, mode, "
                          "targets, budget_s, repeats, tries")
    mode = table.get("mode", "one_at_a_time")
    if mode not in MODES:
        raise ConfigError(_problem(where, "mode", f" = {mode!r}: must be one of {', '.join(MODES)}"))
    knobs = table.get("knobs")
    if not isinstance(knobs, dict) or not knobs:
        raise ConfigError(_problem(where, "knobs", " is missing or empty: name at least one of "
                                   + ", ".join(KNOBS)))
    values = {}
    for name, spec in knobs.items():
        if name not in KNOBS:
            import difflib
            close = difflib.get_close_matches(name, list(KNOBS), n=1)
            raise ConfigError(_problem(where, f"knobs.{name}", ": unknown knob"
                                       + (f" (did you mean '{close[0]}'?)" if close else "")
                                       + "; knobs: " + ", ".join(KNOBS)))
        values[name] = _values(where, name, spec, KNOBS[name])
    targets = table.get("targets", [0.01, 0.05])
    if (not isinstance(targets, list) or not targets
            or not all(isinstance(t, (int, float)) and not isinstance(t, bool) and t > 0
                       for t in targets)):
        raise ConfigError(_problem(where, "targets", f" = {targets!r}: must be a list of "
                                   "relative errors > 0"))
    budget = table.get("budget_s")
    if budget is not None and (isinstance(budget, bool) or not isinstance(budget, (int, float))
                               or not budget > 0):
        raise ConfigError(_problem(where, "budget_s", f" = {budget!r}: must be seconds > 0"))
    counts = {}
    for key, lo, default in (("repeats", 1, 3), ("tries", 1, 3)):
        n = table.get(key, default)
        if isinstance(n, bool) or not isinstance(n, int) or n < lo:
            raise ConfigError(_problem(where, key, f" = {n!r}: must be an integer >= {lo}"))
        counts[key] = n
    return SweepSpec(values, mode, tuple(float(t) for t in targets),
                     None if budget is None else float(budget), **counts)


# ------------------------------------------------------------------------------ variants
def _set(table: dict, path: str, value) -> dict:
    """A copy of the raw scene table with knob ``path`` set to ``value``."""
    out = copy.deepcopy(table)
    if path == "lights.samples":   # every area and environment light
        for light in out.get("lights", []):
            if light.get("type") in ("disc", "environment"):
                light["samples"] = value
        return out
    head, _, key = path.partition(".")
    out.setdefault(head, {})[key] = value
    for p, v in KNOBS[path].also if path in KNOBS else ():
        out = _set(out, p, v)
    return out


def _scene(table: dict, where: str, label: str):
    try:
        return scene_from_dict(table, where=where)
    except ConfigError as exc:
        raise ConfigError(f"sweep point {label}: {exc}") from None


def _current(table: dict, scene, path: str):
    if path == "lights.samples":
        vals = [l.samples for l in scene.lights if l.type in ("disc", "environment")]
        return vals[0] if vals else None
    knob = KNOBS.get(path)
    if knob is not None and any(_current(table, scene, p) != v for p, v in knob.also):
        return None             # e.g. photons while the scene renders with the multipole
    head, _, key = path.partition(".")
    return getattr(getattr(scene, head), key)


@dataclass
class Point:
    knob: str                  # "" for the scene as written; "a=1,b=2" joined for grid points
    values: dict               # knob path -> value
    scene: object
    role: str = "point"        # point | base | reference


def sweep_points(table: dict, where: str, spec: SweepSpec) -> list[Point]:
    """The scene as written, every sweep point and every knob's reference, as scene variants."""
    base = _scene(table, where, "(scene as written)")
    points = [Point("", {}, base, "base")]
    combos = ([{k: v} for k, vals in spec.knobs.items() for v in vals] if spec.mode == "one_at_a_time"
              else [dict(zip(spec.knobs, c)) for c in itertools.product(*spec.knobs.values())])
    for combo in combos:
        t = table
        for k, v in combo.items():
            t = _set(t, k, v)
        label = ",".join(f"{k}={v}" for k, v in combo.items())
        points.append(Point(",".join(combo), combo, _scene(t, where, label)))
    for name, vals in spec.knobs.items():
        knob = KNOBS[name]
        if knob.reference == "brute_force":
            t = _set(table, "bssrdf.brute_force", True)
            points.append(Point(name, {"bssrdf.brute_force": True},
                                _scene(t, where, f"{name} reference"), "reference"))
        elif knob.reference == "monte_carlo":
            t = _set(table, "optics.profile", "monte_carlo")
            points.append(Point(name, {"optics.profile": "monte_carlo"},
                                _scene(t, where, f"{name} reference"), "reference"))
        elif knob.reference == "high_mesh":
            if "high" not in base.render.geometries:
                raise ConfigError(_problem(where, f"knobs.{name}", ": its reference is the high "
                                           'mesh: add "high" to render.geometries'))
        # "finest": the reference is the sweep's own most refined point (no extra render)
    return points


# ------------------------------------------------------------------------------ scoring
IMAGE_STAGES = ("render", "bssrdf", "cycles")   # the nodes whose images a point is scored on


def _keys(scene) -> dict[str, str]:
    """Cache keys of the nodes a sweep point of ``scene`` runs (its images and everything
    they read), computed without running anything."""
    nodes, _ = build_graph(scene)
    keys: dict[str, str] = {}
    for nid in plan_order(nodes, [nid for nid, n in nodes.items() if n.stage in IMAGE_STAGES]):
        keys[nid] = node_key(key_parts(nodes[nid], keys))
    return keys


def idle_knobs(table: dict, where: str, spec: SweepSpec) -> dict[str, str]:
    """Knobs that change no node of the scene: name -> why, for the refusal.

    A knob's values are set one at a time on the scene as written (in either mode); when
    they give every node the sweep runs the same cache key, its points are one and the
    same set of images, and their errors (all 0) would recommend its cheapest value for a
    setting that does nothing (``lights.samples`` on a scene lit by point lights only).  A
    knob with one value is compared with the scene as written where the value differs from
    the scene's own; with one value equal to it there is nothing to compare."""
    base = _scene(table, where, "(scene as written)")
    out = {}
    for name, vals in spec.knobs.items():
        keys = [_keys(_scene(_set(table, name, v), where, f"{name}={v}")) for v in vals]
        if len(vals) == 1:
            if _current(table, base, name) == vals[0]:
                continue
            keys.append(_keys(base))
        if any(k != keys[0] for k in keys[1:]):
            continue
        why = (f"its values {', '.join(map(_fmt, vals))}"
               + (" and the scene's own" if len(vals) == 1 else "")
               + " give every node the sweep runs the same cache key, so the same images")
        if name == "lights.samples":
            rendered = {l.name: l.type for _, group in base.light_groups() for l in group}
            why += (" (lights.samples sets the samples of disc and environment lights; the "
                    "lights rendered are " + (", ".join(f"{t} '{n}'" for n, t in
                                                         rendered.items()) or "none") + ")")
        out[name] = why
    return out


def _images(store, summary) -> dict:
    """(model, light, geometry) -> (cache key, RenderedImage) of the image nodes of a summary."""
    from dermis.pipeline import artifacts
    out = {}
    for rep in summary.nodes:
        if rep.stage in IMAGE_STAGES:
            img = artifacts.load(store.artifact_dir(rep.id, rep.key))
            out[(img.info["model"], img.info["light"], img.info["geometry"])] = (rep.key, img)
    return out


def _flip(image, reference) -> float:
    """Mean LDR FLIP of two linear images tone-mapped with the reference's exposure."""
    import flip_evaluator as flip
    from dermis.reports.tonemap import shared_exposure, tonemap
    e = shared_exposure([reference.linear])
    test, ref = tonemap([image.linear, reference.linear], exposure=e)
    _, mean, _ = flip.evaluate(ref.astype(np.float32) / 255.0, test.astype(np.float32) / 255.0,
                               "LDR")
    return float(mean)


def _errors(images: dict, refs: dict, *, high_mesh: bool = False) -> dict:
    """Mean relative RMSE and FLIP over the images the knob changes.

    An image with the same cache key as its reference is the same artifact (the knob does not
    reach it: the Lafortune image under a gather knob): it is not scored, else every such
    image would pull the mean towards 0.  A point whose images are all its reference's (the
    finest value of a knob) has error 0."""
    from dermis.reports.diff import difference
    rel, flips, same = [], [], 0
    for (model, light, geom), (key, img) in images.items():
        ref = refs.get((model, light, "high" if high_mesh else geom))
        if ref is None or (high_mesh and geom == "high"):
            continue
        if key == ref[0]:
            same += 1
            continue
        rel.append(float(difference(img, ref[1]).metrics["rel_rmse"]))
        flips.append(_flip(img, ref[1]))
    if not rel:
        zero = 0.0 if same else None
        return {"rel_rmse": zero, "rel_rmse_max": zero, "flip": zero, "images": 0,
                "images_unchanged": same}
    return {"rel_rmse": float(np.mean(rel)), "rel_rmse_max": float(np.max(rel)),
            "flip": float(np.mean(flips)), "images": len(rel), "images_unchanged": same}


def _varying(summaries: list) -> set[str]:
    """Ids of the nodes whose key differs between the given runs: what the knob changes."""
    keys: dict[str, set] = {}
    for s in summaries:
        for rep in s.nodes:
            keys.setdefault(rep.id, set()).add(rep.key)
    ids = {nid for nid, ks in keys.items() if len(ks) > 1}
    ids |= {nid for nid in keys if any(nid not in {r.id for r in s.nodes} for s in summaries)}
    return ids


def _seconds(store, summary, varying: set[str]) -> dict:
    """Node seconds from the stage metadata: the nodes the knob changes, and the rest."""
    changed = shared = kernel = 0.0
    for rep in summary.nodes:
        meta = store.meta(rep.id, rep.key)
        s = float(meta.get("seconds", 0.0)) - float(meta.get("build_seconds", 0.0))
        if rep.id in varying:
            changed += s
            kernel += float(meta.get("kernel_seconds", 0.0))
        else:
            shared += s
    return {"changed": changed, "shared": shared, "total": changed + shared, "kernel": kernel}


def pareto_front(points: list[dict]) -> list[int]:
    """Indices of the points no other point beats in both time and error (sorted by time)."""
    idx = [i for i, p in enumerate(points) if p.get("rel_rmse") is not None]
    idx.sort(key=lambda i: (points[i]["seconds"], points[i]["rel_rmse"]))
    front, best = [], math.inf
    for i in idx:
        if points[i]["rel_rmse"] < best:
            front.append(i)
            best = points[i]["rel_rmse"]
    return front


def recommend(points: list[dict], targets, budget_s) -> dict:
    """The cheapest point reaching each error target, and the most accurate within the budget."""
    scored = [p for p in points if p.get("rel_rmse") is not None]
    out = {}
    for t in targets:
        ok = [p for p in scored if p["rel_rmse"] <= t]
        out[f"rel_rmse<={t:g}"] = (min(ok, key=lambda p: p["seconds"])["values"] if ok else None)
    if budget_s is not None:
        ok = [p for p in scored if p["seconds"] <= budget_s]
        out[f"seconds<={budget_s:g}"] = (min(ok, key=lambda p: p["rel_rmse"])["values"]
                                         if ok else None)
    return out


def combos(rows: list[dict], base_seconds: float) -> list[tuple]:
    """Every combination of the swept values of a one-at-a-time sweep with its first-order
    prediction: (seconds, rel_rmse, config, all defaults).

    Model: each knob's error is independent of the others', so errors add in quadrature,
    sqrt(sum e_k^2); its time adds to the scene's, T = T_base + sum (t_k(v) - t_k(default))
    with t_k the seconds of the nodes knob k changes.  A knob whose default is not among its
    values counts its full t_k(v).  Empty when there are more than 500,000 combinations."""
    by: dict[str, list] = {}
    for r in rows:
        if r.get("rel_rmse") is not None and r["knob"] and len(r["values"]) == 1:
            by.setdefault(r["knob"], []).append(r)
    names = sorted(by)
    if not names or math.prod(len(by[k]) for k in names) > 500_000:
        return []
    dflt = {k: next((r["seconds"] for r in by[k] if r["is_default"]), 0.0) for k in names}
    out = []
    for combo in itertools.product(*(by[k] for k in names)):
        t = base_seconds + sum(r["seconds"] - dflt[k] for k, r in zip(names, combo))
        e = math.sqrt(sum(r["rel_rmse"] ** 2 for r in combo))
        out.append((t, e, {k: r["values"][k] for k, r in zip(names, combo)},
                    all(r["is_default"] for r in combo)))
    return out


def combine(rows: list[dict], targets, budget_s, base_seconds: float) -> dict:
    """Settings of every knob together (one-at-a-time sweeps): the cheapest combination of
    swept values predicted to reach each error target, and the most accurate within the
    budget, by the first-order model of :func:`combos` (predictions only: what is
    recommended is rendered first, :mod:`dermis.reports.sweep_verify`)."""
    cands = combos(rows, base_seconds)
    if not cands:
        return {}

    def pick(c):
        return None if c is None else {"values": c[2], "predicted_seconds": c[0],
                                       "predicted_rel_rmse": c[1]}
    out = {"model": "errors in quadrature, times added to the scene's (base_seconds)",
           "base_seconds": base_seconds,
           "defaults": pick(next((c for c in cands if c[3]), None))}
    for t in targets:
        ok = [c for c in cands if c[1] <= t]
        out[f"rel_rmse<={t:g}"] = pick(min(ok, key=lambda c: (c[0], c[1])) if ok else None)
    if budget_s is not None:
        ok = [c for c in cands if c[0] <= budget_s]
        out[f"seconds<={budget_s:g}"] = pick(min(ok, key=lambda c: (c[1], c[0])) if ok else None)
    return out


def run_sweep(scene_path, *, cache, out_dir=None, workers: int = 1, scheduler: str | None = None,
              device: str | None = None, progress=None) -> dict:
    """Run every point of the scene's ``[sweep]``; write and return the results."""
    from dermis.pipeline.distributed import run_graphs
    from dermis.pipeline.store import Store

    path = Path(scene_path)
    where = str(path)
    try:
        table = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{where}: scene file does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None
    if "sweep" not in table:
        raise ConfigError(f"{where}: no [sweep] table: name the knobs to sweep, e.g. "
                          '[sweep.knobs] "bssrdf.epsilon" = [1.0, 0.5, 0.2]')
    spec = parse_sweep(table.pop("sweep"), where)
    points = sweep_points(table, where, spec)
    idle = idle_knobs(table, where, spec)
    if idle:   # refused before any node runs
        raise ConfigError("\n".join(f"{where}: sweep.knobs.{name}: has no effect on this "
                                     f"scene: {why}; remove it from [sweep.knobs]"
                                     for name, why in idle.items()))
    graphs = [_image_graph(p.scene) for p in points]
    run_kw = {"workers": workers, "scheduler": scheduler, "device": device}
    summaries, stats = run_graphs(graphs, cache, progress=progress, warm=WARM_IMPORTS, **run_kw)
    store = Store(cache)
    groups = {}
    for i, p in enumerate(points):
        if p.role == "point":
            groups.setdefault(p.knob if spec.mode == "one_at_a_time" else "grid", []).append(i)
    by_role = {(p.role, p.knob): i for i, p in enumerate(points)}
    # what a knob changes: the nodes whose keys differ among its points and its reference
    # (with one value swept, the reference is what it is measured against)
    varying = {g: _varying([summaries[i] for i in idx]
                           + ([summaries[by_role[("reference", g)]]]
                              if ("reference", g) in by_role else []))
               for g, idx in groups.items()}
    images = [_images(store, s) for s in summaries]
    rows, at = [], []
    for i, p in enumerate(points):
        if p.role != "point":
            continue
        errs, ref = {}, "finest"
        if spec.mode == "one_at_a_time":
            knob = KNOBS[p.knob]
            ref = knob.reference
            if knob.reference in ("brute_force", "monte_carlo"):
                errs = _errors(images[i], images[by_role[("reference", p.knob)]])
            elif knob.reference == "high_mesh":
                errs = _errors(images[i], images[0], high_mesh=True)
            else:
                finest = max(spec.knobs[p.knob], key=knob.rank)
                j = next(k for k, q in enumerate(points)
                         if q.role == "point" and q.knob == p.knob and q.values[p.knob] == finest)
                errs = _errors(images[i], images[j])
        else:   # grid: against the most refined corner
            j = max((k for k, q in enumerate(points) if q.role == "point"),
                    key=lambda k: sum(KNOBS[n].rank(v) for n, v in points[k].values.items()))
            errs = _errors(images[i], images[j])
        default = all(_current(table, points[0].scene, k) == v for k, v in p.values.items())
        rows.append({"knob": p.knob, "values": p.values, "is_default": default,
                     "error_reference": ref, **errs})
        at.append(i)
    # cost: every point's changed nodes (the scene as written: every node any knob changes)
    # timed `repeats` times in rotated order; the median with its min-max spread
    union = set().union(*varying.values())
    ids = [[r.id for r in summaries[i].nodes
            if r.id in varying[rows[n]["knob"] if spec.mode == "one_at_a_time" else "grid"]]
           for n, i in enumerate(at)] + [[r.id for r in summaries[0].nodes if r.id in union]]
    timed = _timed(store, [summaries[i] for i in at] + [summaries[0]],
                   [graphs[i][0] for i in at] + [graphs[0][0]], ids, cache, spec.repeats, device)
    for r, t in zip(rows, timed):
        r.update(t)
    base_total = timed[-1]["seconds_total"]
    extrap = _converged(rows, spec) if spec.mode == "one_at_a_time" else {}
    result = {"scene": where, "mode": spec.mode, "targets": list(spec.targets),
              "budget_s": spec.budget_s, "repeats": spec.repeats, "points": rows,
              "fronts": {}, "per_knob": {}, "distributed": stats.to_dict(),
              "reference_rules": {k: KNOBS[k].reference for k in spec.knobs},
              "extrapolation": extrap, "base_seconds": base_total,
              "base_seconds_spread": [timed[-1]["seconds_min"] + timed[-1]["seconds_shared"],
                                      timed[-1]["seconds_max"] + timed[-1]["seconds_shared"]]}
    for name in ({p["knob"] for p in rows} if spec.mode == "one_at_a_time" else {""}):
        sel = [k for k, r in enumerate(rows) if r["knob"] == name or spec.mode == "grid"]
        front = pareto_front([rows[k] for k in sel])
        result["fronts"][name or "grid"] = [sel[k] for k in front]
        result["per_knob"][name or "grid"] = recommend([rows[k] for k in sel], spec.targets,
                                                       spec.budget_s)
    # across knobs only whole-scene times compare: each point's total node seconds
    total = [{**r, "seconds": r["seconds_total"]} for r in rows]
    result["fronts"]["joint"] = pareto_front(total)
    result["per_knob"]["joint"] = recommend(total, spec.targets, spec.budget_s)
    if spec.mode == "one_at_a_time":
        result["combined"] = combine(rows, spec.targets, spec.budget_s, base_total)
        result["recommended"] = _verified(table, where, spec, rows, result, summaries[0],
                                          union, cache, run_kw)
    else:   # every grid point is a rendered configuration: its measurement is the check
        result["recommended"] = {}
        for key, t, b in _goals(spec):
            cands = [(r["seconds_total"], r["rel_rmse"], r["values"]) for r in rows
                     if r.get("rel_rmse") is not None]
            measured = {config_id(r["values"]): {"rel_rmse": r["rel_rmse"],
                                                 "seconds": r["seconds_total"]} for r in rows}
            rec = choose(candidates(cands, t, b, 1), measured, t, b)
            rec["predicted"] = None        # measured, not predicted
            result["recommended"][key] = rec
    out = Path(out_dir) if out_dir else Path(points[0].scene.output.output_dir) / \
        points[0].scene.scene.name / "sweep"
    out.mkdir(parents=True, exist_ok=True)
    (out / "sweep.json").write_text(json.dumps(result, indent=1, default=str))
    plots(result, out)
    return result


def _image_graph(scene):
    """The scene's graph and its image nodes: only the images are scored (the images /
    differences / report nodes would be work, and failure modes, the sweep never reads)."""
    nodes, _ = build_graph(scene)
    return nodes, [nid for nid, n in nodes.items() if n.stage in IMAGE_STAGES]


def _timed(store, summaries, graphs, ids, cache, repeats, device) -> list[dict]:
    """Seconds of each run: the nodes ``ids[i]`` timed ``repeats`` times (the first from the
    run's own metadata), median and spread, plus the rest from the metadata (shared)."""
    extra = repeat_seconds(graphs, ids, cache, repeats, device)
    out = []
    for s, own, more in zip(summaries, ids, extra):
        secs = _seconds(store, s, set(own))
        sp = spread([secs["changed"], *more])
        out.append({**sp, "seconds_first": secs["changed"], "seconds_shared": secs["shared"],
                    "seconds_total": sp["seconds"] + secs["shared"],
                    "kernel_seconds": secs["kernel"]})
    return out


def _converged(rows: list[dict], spec: SweepSpec) -> dict:
    """Errors against the converged answer: a knob measured against its own finest value gets
    that value's extrapolated error added (triangle inequality) and stated as uncertainty."""
    out = {}
    for name, vals in spec.knobs.items():
        knob = KNOBS[name]
        mine = sorted((r for r in rows if r["knob"] == name), key=lambda r: knob.rank(
            r["values"][name]))
        if knob.reference != "finest" or knob.choices or not mine:
            for r in mine:
                r["error_uncertainty"] = 0.0 if r.get("rel_rmse") is not None else None
            continue
        ex = extrapolate([r["values"][name] for r in mine], [r.get("rel_rmse") for r in mine],
                         knob.finer, knob.order, noise=knob.order == 0.5)
        out[name] = ex
        if ex["finest_error"] is None:
            continue
        for r in mine:
            if r.get("rel_rmse") is None:
                continue
            r["rel_rmse_vs_finest"] = r["rel_rmse"]
            r["rel_rmse"] = r["rel_rmse"] + ex["finest_error"]
            r["error_uncertainty"] = ex["finest_error"]
            r["error_reference"] = "extrapolated"
    return out


def _goals(spec: SweepSpec):
    """(key, error target, time budget) of each recommendation."""
    yield from ((f"rel_rmse<={t:g}", t, None) for t in spec.targets)
    if spec.budget_s is not None:
        yield f"seconds<={spec.budget_s:g}", None, spec.budget_s


def _verified(table, where, spec, rows, result, base_summary, union, cache, run_kw) -> dict:
    """Render the candidate configurations of every goal (and the defaults) and the most
    refined configuration; recommend, per goal, the first candidate whose measurement meets
    it.  Measured error: relative RMSE against the most refined configuration (every knob at
    its finest value, the brute-force gather / Monte Carlo profile where a knob's reference
    is one) plus that configuration's own error bound, the sum of the knobs' extrapolated
    finest errors (triangle inequality).  Measured seconds: as for the points."""
    from dermis.pipeline.distributed import run_graphs
    from dermis.pipeline.store import Store
    all_c = combos(rows, result["base_seconds"])
    plans = {key: candidates(all_c, t, b, spec.tries) for key, t, b in _goals(spec)}
    configs = {config_id(c[2]): c[2] for cs in plans.values() for c in cs}
    dflt = next((c for c in all_c if c[3]), None)
    written = _scene(table, where, "(scene as written)")
    mine = {k: _current(table, written, k) for k in spec.knobs}   # the scene as written
    configs.setdefault(config_id(mine), mine)
    ref_t = table
    for name, vals in spec.knobs.items():
        ref_t = _set(ref_t, name, max(vals, key=KNOBS[name].rank))
        extra = {"brute_force": ("bssrdf.brute_force", True),
                 "monte_carlo": ("optics.profile", "monte_carlo")}.get(KNOBS[name].reference)
        if extra:
            ref_t = _set(ref_t, *extra)
    scenes = []
    for cid, cfg in configs.items():
        t = table
        for k, v in cfg.items():
            t = t if v is None else _set(t, k, v)
        scenes.append(_scene(t, where, cid))
    scenes.append(_scene(ref_t, where, "most refined configuration"))
    graphs = [_image_graph(sc) for sc in scenes]
    summaries, _ = run_graphs(graphs, cache, warm=WARM_IMPORTS, **run_kw)
    store = Store(cache)
    base_keys = {r.id: r.key for r in base_summary.nodes}
    ids = [[r.id for r in s.nodes if r.id in union or base_keys.get(r.id) != r.key]
           for s in summaries[:-1]]
    timed = _timed(store, summaries[:-1], [g[0] for g in graphs[:-1]], ids, cache,
                   spec.repeats, run_kw["device"])
    ref_imgs = _images(store, summaries[-1])
    ref_err = sum(e["finest_error"] or 0.0 for e in result["extrapolation"].values())
    high = any(KNOBS[k].reference == "high_mesh" for k in spec.knobs)
    measured = {}
    for cid, s, t in zip(configs, summaries, timed):
        e = _errors(_images(store, s), ref_imgs, high_mesh=high)
        err = None if e["rel_rmse"] is None else e["rel_rmse"] + ref_err
        measured[cid] = {"rel_rmse": err, "rel_rmse_vs_most_refined": e["rel_rmse"],
                         "reference_error": ref_err, "flip": e["flip"],
                         "seconds": t["seconds_total"],
                         "seconds_spread": [t["seconds_min"] + t["seconds_shared"],
                                            t["seconds_max"] + t["seconds_shared"]],
                         "seconds_samples": t["seconds_samples"]}
    out = {key: choose(plans[key], measured, t, b) for key, t, b in _goals(spec)}
    # the scene as written, rendered and measured like the candidates (predicted where its
    # values are among the swept ones)
    out["defaults"] = {"config": mine, "measured": measured[config_id(mine)], "meets": None,
                       "predicted": None if dflt is None else {"rel_rmse": dflt[1],
                                                               "seconds": dflt[0]}}
    return out


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


# ------------------------------------------------------------------------------ CLI
def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("sweep", help="speed-accuracy sweep of the scene's [sweep] knobs")
    p.add_argument("scene", help="scene TOML with a [sweep] table")
    p.add_argument("--cache", help="cache directory (shared by every worker)")
    p.add_argument("--out", help="output folder (default output_dir/<scene>/sweep)")
    p.add_argument("--workers", type=int, default=1,
                   help="local worker processes (Dask LocalCluster when > 1)")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler")
    p.add_argument("--device", help="OpenCL device spec")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from dermis.pipeline.api import cache_dir_for
    if args.workers < 1:
        raise DermisError(f"--workers {args.workers}: must be >= 1")

    def progress(done, running, failed, total):
        print(f"\rsweep: {done}/{total} tasks done, {running} running, {failed} failed",
              end="", flush=True)

    res = run_sweep(args.scene, cache=cache_dir_for(None, args.cache), out_dir=args.out,
                    workers=args.workers, scheduler=args.scheduler, device=args.device,
                    progress=progress)
    print()
    print(f"{'knob':<28} {'value':>12} {'seconds':>9} {'min-max':>13} {'rel RMSE':>9} "
          f"{'+-':>7} {'FLIP':>7}  reference")
    for r in res["points"]:
        for k, v in r["values"].items():
            err = "-" if r.get("rel_rmse") is None else f"{r['rel_rmse']:.4f}"
            fl = "-" if r.get("flip") is None else f"{r['flip']:.4f}"
            mark = " *" if r["is_default"] else ""
            unc = "-" if r.get("error_uncertainty") is None else f"{r['error_uncertainty']:.4f}"
            mm = f"{r['seconds_min']:.2f}-{r['seconds_max']:.2f}"
            print(f"{k:<28} {_fmt(v):>12} {r['seconds']:>9.2f} {mm:>13} {err:>9} {unc:>7} "
                  f"{fl:>7}  {r['error_reference']}{mark}")
    for goal, rec in res["recommended"].items():
        if goal == "defaults":
            continue
        tried = len(rec["misses"]) + (rec["config"] is not None)
        if rec["config"] is None:
            print(f"recommended for {goal}: none: " + (
                f"of the {tried} configurations rendered none met it (sweep.json lists them)"
                if tried else "no combination of the swept values is predicted to meet it"))
            continue
        m, pr = rec["measured"], rec["predicted"]
        print(f"recommended for {goal}: " + ", ".join(f"{k} = {_fmt(v)}" for k, v in
                                                     rec["config"].items())
              + f"  (rendered: rel RMSE {m['rel_rmse']:.4f}, {m['seconds']:.2f} s"
              + (f"; predicted {pr['rel_rmse']:.4f}, {pr['seconds']:.2f} s" if pr else "")
              + (f"; {tried - 1} cheaper candidate(s) missed when rendered" if tried > 1 else "")
              + ")")
    return 0
