"""``[render] models = ["auto"]``: per view and lighting condition, the cheapest model that
the measured evidence says stays within ``[report] accuracy`` of the path-traced truth in
every face region.

The evidence (:data:`EVIDENCE`) is the default scene's: for each kind of lighting condition
(the types of its lights, and whether the main camera or a close-up sees it) every model's
seconds per image and its worst region bound ``|error| + 2 s.e.`` against the reference,
over every condition of that kind (``bench/bench_requirements.py``,
``bench/results/requirements.json``).  A scene's condition takes the evidence of its kind;
a kind the evidence lacks takes the worst bound of every kind (a model is trusted only where
it was trusted everywhere).  No model meeting the accuracy: the most accurate one, the
smallest RMS of its region errors (the bound is dominated by the reference's noise in small
regions; the RMS by what the model gets wrong).
The report then verifies the choice against the reference on that view (``views.<view>.
auto`` in metrics.json: whether the target held in every region).
"""
from __future__ import annotations

from dermis.pipeline.errors import ConfigError

__all__ = ["AUTO", "EVIDENCE", "condition_kind", "choose", "choice_problems"]

AUTO = "auto"

# kind -> model -> (seconds per image, worst region bound |error| + 2 s.e., RMS of the region
# errors): bench/results/requirements.json (default scene, 2 cores; the BSSRDF's seconds
# include its irradiance pass)
EVIDENCE: dict[str, dict[str, tuple[float, float, float]]] = {
    "directional/face": {
        "asperity": (0.37, 0.494, 0.137),
        "hk93": (0.45, 0.544, 0.190),
        "lafortune": (0.88, 0.514, 0.140),
        "bssrdf": (10.56, 0.518, 0.141),
        "bssrdf_mc": (11.15, 0.518, 0.141),
    },
    "disc/close-up": {
        "asperity": (0.41, 0.053, 0.006),
        "hk93": (0.53, 0.140, 0.097),
        "lafortune": (0.76, 0.073, 0.024),
        "bssrdf_mc": (22.27, 0.064, 0.016),
        "bssrdf": (22.83, 0.064, 0.016),
    },
    "disc/face": {
        "lafortune": (1.38, 0.371, 0.092),
        "hk93": (1.42, 0.413, 0.154),
        "asperity": (1.57, 0.337, 0.089),
        "bssrdf_mc": (27.02, 0.397, 0.103),
        "bssrdf": (27.56, 0.397, 0.103),
    },
    "environment/face": {
        "asperity": (0.91, 0.257, 0.094),
        "hk93": (1.43, 0.310, 0.163),
        "lafortune": (1.51, 0.228, 0.073),
        "bssrdf_mc": (35.48, 0.254, 0.080),
        "bssrdf": (35.90, 0.254, 0.080),
    },
    "point/close-up": {
        "asperity": (0.20, 0.829, 0.164),
        "lafortune": (0.20, 0.875, 0.184),
        "hk93": (0.25, 0.686, 0.180),
        "bssrdf_mc": (6.17, 0.862, 0.196),
        "bssrdf": (6.70, 0.864, 0.197),
    },
    "point/face": {
        "asperity": (0.23, 0.362, 0.096),
        "lafortune": (0.42, 0.395, 0.097),
        "hk93": (0.54, 0.436, 0.158),
        "bssrdf_mc": (13.65, 0.408, 0.099),
        "bssrdf": (14.10, 0.408, 0.099),
    },
}


def condition_kind(light_types, close_up: bool) -> str:
    """``<types of its lights, sorted, +-joined>/<face | close-up>``, e.g. ``point/close-up``."""
    return f"{'+'.join(sorted(set(light_types)))}/{'close-up' if close_up else 'face'}"


def _evidence(kind: str) -> dict:
    if kind in EVIDENCE:
        return EVIDENCE[kind]
    worst: dict = {}
    for models in EVIDENCE.values():
        for m, (t, b, e) in models.items():
            t0, b0, e0 = worst.get(m, (0.0, 0.0, 0.0))
            worst[m] = (max(t, t0), max(b, b0), max(e, e0))
    return worst


def choose(kind: str, accuracy: float, registered, where: str) -> str:
    """The model ``["auto"]`` renders for a lighting condition of ``kind``."""
    evidence = {m: v for m, v in _evidence(kind).items() if m in registered}
    if not evidence:
        raise ConfigError(f"{where}: render.models = [\"auto\"]: no measured evidence for "
                          f"any registered model ({', '.join(registered)})")
    meets = sorted((t, m) for m, (t, b, _) in evidence.items() if b <= accuracy)
    if meets:
        return meets[0][1]
    return min(evidence.items(), key=lambda kv: (kv[1][2], kv[1][0]))[0]


def choice_problems(models: tuple, where: str) -> list[str]:
    """``"auto"`` must be the only entry of render.models."""
    if AUTO in models and len(models) > 1:
        return [f"{where}: render.models = {list(models)}: \"auto\" chooses the models itself; "
                "give it alone (render.models = [\"auto\"]) or list models without it"]
    return []
