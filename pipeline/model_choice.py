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
# errors): bench/results/requirements.json (a cold default run on 2 idle cores, references
# at 1.2-6.3 % region noise; the BSSRDF's seconds include its irradiance pass)
EVIDENCE: dict[str, dict[str, tuple[float, float, float]]] = {
    "directional/face": {
        "asperity": (0.30, 0.210, 0.092),
        "lambert": (0.35, 0.229, 0.095),
        "lafortune": (0.37, 0.242, 0.086),
        "hk93": (0.45, 0.289, 0.164),
        "bssrdf_single": (3.93, 0.247, 0.084),
        "bssrdf_mc": (4.52, 0.247, 0.084),
        "bssrdf": (7.33, 0.247, 0.084),
    },
    "disc/close-up": {
        "asperity": (0.12, 0.080, 0.047),
        "hk93": (0.20, 0.164, 0.134),
        "lafortune": (0.27, 0.052, 0.018),
        "lambert": (0.28, 0.096, 0.063),
        "bssrdf_single": (5.80, 0.060, 0.026),
        "bssrdf_mc": (5.94, 0.060, 0.026),
        "bssrdf": (6.15, 0.060, 0.026),
    },
    "disc/face": {
        "asperity": (0.40, 0.233, 0.079),
        "hk93": (0.61, 0.304, 0.151),
        "lambert": (0.66, 0.245, 0.086),
        "lafortune": (0.78, 0.254, 0.081),
        "bssrdf_single": (7.05, 0.285, 0.093),
        "bssrdf_mc": (7.45, 0.284, 0.093),
        "bssrdf": (7.95, 0.284, 0.093),
    },
    "environment/face": {
        "asperity": (0.48, 0.200, 0.083),
        "lambert": (0.63, 0.198, 0.088),
        "lafortune": (0.71, 0.168, 0.060),
        "hk93": (0.80, 0.261, 0.156),
        "bssrdf_single": (13.61, 0.178, 0.068),
        "bssrdf_mc": (13.98, 0.178, 0.068),
        "bssrdf": (14.98, 0.178, 0.068),
    },
    "point/close-up": {
        "asperity": (0.05, 0.247, 0.099),
        "lafortune": (0.06, 0.277, 0.124),
        "hk93": (0.10, 0.316, 0.172),
        "lambert": (0.14, 0.261, 0.116),
        "bssrdf": (2.34, 0.351, 0.148),
        "bssrdf_single": (2.40, 0.354, 0.150),
        "bssrdf_mc": (2.71, 0.351, 0.148),
    },
    "point/face": {
        "lambert": (0.16, 0.251, 0.102),
        "asperity": (0.20, 0.219, 0.093),
        "hk93": (0.21, 0.310, 0.165),
        "lafortune": (0.43, 0.260, 0.091),
        "bssrdf_single": (3.69, 0.276, 0.091),
        "bssrdf_mc": (5.04, 0.276, 0.091),
        "bssrdf": (5.36, 0.276, 0.091),
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
