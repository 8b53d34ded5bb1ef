"""What makes a ``dermis sweep`` trustworthy: repeated timings, a converged reference, and
recommendations that were rendered before they are made.

* Cost (:func:`repeat_seconds`): each point's changed nodes are recomputed ``repeats - 1``
  more times in this process (forced, their cache entries kept), in an order rotated from
  round to round so that no point always runs first (first kernel launches, warm caches,
  background load drift); a point's cost is the median of its samples, with the min and max.
* Error (:func:`extrapolate`): a knob whose reference is its own finest value is scored
  against an extrapolation to the converged answer: with h the knob's step (1/value for a
  knob that refines upwards, the value for one that refines downwards) and
  ``|I(h) - I(0)| = C h^p``, the finest point's own error follows from its distance
  ``d_{n-1}`` to the next-finest: ``d_{n-1} h_n^p / (h_{n-1}^p - h_n^p)`` where the errors
  share a direction (Richardson 1911), ``d_{n-1} / sqrt(1 + (h_{n-1}/h_n)^2p)`` where they
  are independent Monte Carlo noise; the order p (and the model) fitted from the three
  finest values, else the knob's stated ones.
  Every point's error is then bounded by the triangle inequality: distance to the finest plus
  the finest's error, which is also stated as the error's uncertainty.
* Recommendations (:func:`choose`): the candidate configurations predicted to meet a target
  (first order: errors in quadrature, times added) are rendered; one is recommended only if
  its measured error meets the target, else the next is tried, and the misses are listed
  with predicted and measured values.
"""
from __future__ import annotations

import math
import statistics

__all__ = ["repeat_seconds", "spread", "extrapolate", "candidates", "choose", "config_id"]


# --------------------------------------------------------------------------- cost
def repeat_seconds(nodes_of: list, ids_of: list[list[str]], cache, repeats: int,
                   device=None) -> list[list[float]]:
    """Extra timing samples: for point i, ``repeats - 1`` forced recomputations of its nodes
    ``ids_of[i]`` (a subset of the graph ``nodes_of[i]``); returns one list of samples per
    point (seconds summed over its nodes, OpenCL program builds excluded).

    Rounds visit the points in an order rotated by one each round, so each point runs at a
    different place in the sequence (run-order effects fall on no point systematically)."""
    from dermis.pipeline.api import RunContext
    from dermis.pipeline.cl import build_seconds
    from dermis.pipeline.graph import execute
    from dermis.pipeline.store import Store
    store = Store(cache)
    n = len(ids_of)
    out: list[list[float]] = [[] for _ in range(n)]
    todo = [i for i in range(n) if ids_of[i]]
    for r in range(max(0, repeats - 1)):
        shift = ((r + 1) * len(todo)) // repeats
        for i in todo[shift:] + todo[:shift]:
            total = 0.0
            for nid in ids_of[i]:
                b0 = build_seconds()
                with store.locked():
                    summary = execute(nodes_of[i], [nid], store, RunContext(device=device),
                                      force=(nid,))
                rep = next(x for x in summary.nodes if x.id == nid)
                total += rep.seconds - (build_seconds() - b0)
            out[i].append(total)
    return out


def spread(samples: list[float]) -> dict:
    """Median with its min-max spread (the samples as measured)."""
    return {"seconds": statistics.median(samples), "seconds_min": min(samples),
            "seconds_max": max(samples), "seconds_samples": list(samples)}


# --------------------------------------------------------------------------- error
def _step(value, finer: str) -> float:
    return 1.0 / float(value) if finer == "higher" else float(value)


def _bisect(f, want: float) -> float | None:
    """p in [0.05, 6] with f(p) = want (f increasing), or None."""
    lo, hi = 0.05, 6.0
    if not f(lo) <= want <= f(hi):
        return None
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < want else (lo, mid)
    return 0.5 * (lo + hi)


def _order(h: list[float], d: list[float], noise: bool) -> float | None:
    """The order p that fits the distances d of h[0] > h[1] to the finest h[2] (or None).

    bias (errors share one direction): d_i = C (h_i^p - h_2^p);
    noise (errors independent between values): d_i^2 = C^2 (h_i^2p + h_2^2p)."""
    if not (h[0] > h[1] > h[2] > 0 and d[0] is not None and d[1] and d[0] > d[1] > 0):
        return None
    if noise:
        return _bisect(lambda p: (h[0] ** (2 * p) + h[2] ** (2 * p))
                       / (h[1] ** (2 * p) + h[2] ** (2 * p)), (d[0] / d[1]) ** 2)
    return _bisect(lambda p: (h[0] ** p - h[2] ** p) / (h[1] ** p - h[2] ** p), d[0] / d[1])


def _finest_error(h1: float, hn: float, d1: float, p: float, noise: bool) -> float:
    if noise:
        return float(d1 / math.sqrt(1.0 + (h1 / hn) ** (2 * p)))
    return float(d1 * hn ** p / (h1 ** p - hn ** p))


def extrapolate(values: list, errors: list[float], finer: str, order: float,
                noise: bool = False) -> dict:
    """The finest value's own error, extrapolated from the finest ones.

    ``values`` sorted coarse to fine, ``errors`` their distance (relative RMSE) to the finest
    (the last is 0).  Two models of how a value's error |I(h) - I(0)| = C h^p relates to
    the distances: bias (the errors of all values point one way, Richardson's case) and
    noise (independent Monte Carlo errors, adding in quadrature).  The model whose order fits
    the three finest distances is used (both: the larger finest error); neither: the knob's
    stated model (``noise``) and ``order``.  A fitted order below half the stated one is
    refused: the values are then outside the asymptotic range, where the bias model's
    amplification 1 / ((h_{n-1}/h_n)^p - 1) diverges as p -> 0 (the observed order checked
    against the formal one, as in Roache's grid-convergence practice, docs/references.md).  Returns ``{"model", "order", "order_from",
    "finest_error"}``; ``finest_error`` is None with fewer than two values."""
    if len(values) < 2 or errors[-2] is None:
        return {"model": "noise" if noise else "bias", "order": order,
                "order_from": "stated for the knob", "finest_error": None}
    h = [_step(v, finer) for v in values]
    h1, hn, d1 = h[-2], h[-1], errors[-2]
    fits = []
    if len(values) >= 3:
        for model in (False, True):
            p = _order(h[-3:], errors[-3:], model)
            if p is not None and p >= 0.5 * order:
                fits.append((_finest_error(h1, hn, d1, p, model), model, p))
    if fits:
        e, model, p = max(fits)
        src = "fit of the three finest values"
    else:
        e, model, p = _finest_error(h1, hn, d1, order, noise), noise, order
        src = "stated for the knob"
    return {"model": "noise" if model else "bias", "order": p, "order_from": src,
            "finest_error": e}


# --------------------------------------------------------------------------- recommendations
def config_id(config: dict) -> str:
    return ",".join(f"{k}={config[k]}" for k in sorted(config))


def candidates(combos: list[tuple], target: float | None, budget: float | None,
               tries: int) -> list[tuple]:
    """Up to ``tries`` combinations (predicted seconds, predicted error, config) to render for
    an error target (cheapest predicted first) or a time budget (most accurate first)."""
    if target is not None:
        ok = sorted((c for c in combos if c[1] <= target), key=lambda c: (c[0], c[1]))
    else:
        ok = sorted((c for c in combos if c[0] <= budget), key=lambda c: (c[1], c[0]))
    return ok[:tries]


def choose(cands: list[tuple], measured: dict, target: float | None = None,
           budget: float | None = None) -> dict:
    """The first candidate whose rendered measurement meets the target (error <= target, or
    seconds <= budget): ``{"config", "predicted", "measured", "meets", "misses"}``; the
    misses tried before it (or all, when none met) are listed with predicted and measured.

    ``measured[config_id(config)]`` = ``{"rel_rmse": ..., "seconds": ...}``."""
    misses = []
    for secs, err, config, *_ in cands:
        m = measured.get(config_id(config))
        entry = {"config": config, "predicted": {"rel_rmse": err, "seconds": secs},
                 "measured": m}
        if m is None or m.get("rel_rmse") is None:
            entry["meets"] = False
            misses.append(entry)
            continue
        entry["meets"] = bool(m["rel_rmse"] <= target if target is not None
                              else m["seconds"] <= budget)
        if entry["meets"]:
            return {**entry, "misses": misses}
        misses.append(entry)
    return {"config": None, "predicted": None, "measured": None, "meets": False,
            "misses": misses}
