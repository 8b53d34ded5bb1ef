"""Layer stacks for the layer-optics stage: dataclasses, validation from TOML, skin presets.

A stack is listed top to bottom.  Units (docs/science.md conventions): thickness in mm
(``math.inf`` allowed for the last layer only), coefficients in 1/mm, per RGB channel.
``sigma_s_prime`` is the reduced scattering coefficient; ``g`` (Henyey-Greenstein mean
cosine) matters only to the Monte Carlo reference and the HK93 model, which use
sigma_s = sigma_s_prime / (1 - g).

Validation rules (each error names file/key, the value and the rule):

* ``thickness_mm`` >= 0 (0 is allowed and means "no layer": the identity), or ``"inf"``
  for the last layer only;
* ``eta`` >= 1 for every layer and for ``eta_above``/``eta_below`` (a relative index
  below 1 across a boundary is still possible between two layers; an absolute index
  below 1 is not a material the models describe);
* ``sigma_a`` >= 0, ``sigma_s_prime`` >= 0 (or ``sigma_s`` >= 0), and
  ``sigma_a + sigma_s_prime`` > 0 per channel (a vacuum layer has no diffusion profile);
* ``g`` in the open interval (-1, 1);
* every value finite; unknown keys are errors (all listed, with a did-you-mean).
"""
from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dermis.pipeline.errors import ConfigError

__all__ = ["Layer", "LayerStack", "Optics", "parse_layer_stack", "load_layers_toml", "PRESETS",
           "PROFILE_MODELS", "PROFILE_KEYS", "DEFAULT_PROFILE_MODEL", "DEFAULT_MC_PHOTONS",
           "DEFAULT_MC_SEED", "split_profile_options", "with_profile"]

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Layer:
    """One homogeneous layer: thickness (mm, may be ``math.inf``), eta, RGB coefficients (1/mm)."""

    thickness_mm: float
    eta: float
    sigma_a: Vec3
    sigma_s_prime: Vec3
    g: float = 0.0

    @property
    def sigma_s(self) -> Vec3:
        """Scattering coefficient sigma_s = sigma_s' / (1 - g) (similarity relation), 1/mm."""
        return tuple(s / (1.0 - self.g) for s in self.sigma_s_prime)  # type: ignore[return-value]

    def to_dict(self) -> dict:
        return {
            "thickness_mm": "inf" if math.isinf(self.thickness_mm) else float(self.thickness_mm),
            "eta": float(self.eta),
            "sigma_a": [float(v) for v in self.sigma_a],
            "sigma_s_prime": [float(v) for v in self.sigma_s_prime],
            "g": float(self.g),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Layer":
        """Inverse of :meth:`to_dict` (exact: the dict holds Python floats)."""
        t = d["thickness_mm"]
        return cls(math.inf if t == "inf" else float(t), float(d["eta"]),
                   tuple(float(v) for v in d["sigma_a"]),
                   tuple(float(v) for v in d["sigma_s_prime"]), float(d["g"]))


@dataclass(frozen=True)
class LayerStack:
    """Layers top to bottom between a medium above (``eta_above``) and below (``eta_below``)."""

    layers: tuple[Layer, ...]
    eta_above: float = 1.0
    eta_below: float = 1.0

    def to_dict(self) -> dict:
        """Canonical JSON-able form (used in cache keys and artifact info)."""
        return {
            "layers": [lay.to_dict() for lay in self.layers],
            "eta_above": float(self.eta_above),
            "eta_below": float(self.eta_below),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "LayerStack":
        """Inverse of :meth:`to_dict`."""
        return cls(tuple(Layer.from_dict(x) for x in d["layers"]), float(d["eta_above"]),
                   float(d["eta_below"]))

    def nonzero(self) -> "LayerStack":
        """The same stack without zero-thickness layers (they are the identity)."""
        return LayerStack(tuple(l for l in self.layers if l.thickness_mm > 0),
                          self.eta_above, self.eta_below)


# ---------------------------------------------------------------------------------------
# The profile model the BSSRDF renders with: [optics] profile / photons / seed
# (docs/profiles.md).

PROFILE_MODELS = ("multipole", "monte_carlo")
PROFILE_KEYS = ("profile", "photons", "seed")
# Diffusion stays the default: it needs no OpenCL device and takes ~1-3 s; the Monte Carlo
# table is the reference (docs/profiles.md: where diffusion is still off, and by how much).
DEFAULT_PROFILE_MODEL = "multipole"
# Photons per channel of the Monte Carlo table, on average (the channels share 3 x this by a
# pilot run, optics/monte_carlo_table.py MC_PILOT): bench/bench_profile_table.py measured <= 1 %
# relative noise per ring over [0.05, 5] mm on two_layer in all channels with this many
# (bench/results/profiles_table.json; 0.95 % at most).
DEFAULT_MC_PHOTONS = 2_400_000
DEFAULT_MC_SEED = 0
MAX_MC_PHOTONS = 2_000_000_000


@dataclass(frozen=True)
class Optics(LayerStack):
    """The scene's ``[optics]``: a layer stack plus the profile model the BSSRDF uses.

    ``to_dict`` (inherited) is the stack alone, so nodes that read only the layers (sample
    spacing, HK93) do not change key when the profile model does.
    """

    profile: str = DEFAULT_PROFILE_MODEL
    photons: int = DEFAULT_MC_PHOTONS
    seed: int = DEFAULT_MC_SEED


def with_profile(stack: LayerStack, profile: str = DEFAULT_PROFILE_MODEL,
                 photons: int = DEFAULT_MC_PHOTONS, seed: int = DEFAULT_MC_SEED) -> Optics:
    """``stack`` as :class:`Optics` with the given profile model."""
    return Optics(stack.layers, stack.eta_above, stack.eta_below, profile, int(photons), int(seed))


def split_profile_options(table: dict, *, where: str) -> tuple[dict, dict, list[str]]:
    """Take the profile-model keys out of an ``[optics]`` table.

    Returns (the table without them, {profile, photons, seed} as given and validated, the
    problems found).  ``profile`` is one of ``PROFILE_MODELS``; ``photons`` (per channel of
    the Monte Carlo table) an integer in 1 .. 2e9; ``seed`` an integer in 0 .. 2**32 - 1.
    """
    rest = {k: v for k, v in table.items() if k not in PROFILE_KEYS}
    opts: dict = {}
    problems: list[str] = []
    if "profile" in table:
        v = table["profile"]
        if v not in PROFILE_MODELS:
            close = difflib.get_close_matches(str(v), PROFILE_MODELS, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            problems.append(f"{where}.profile = {v!r}: must be one of "
                            + ", ".join(f'"{m}"' for m in PROFILE_MODELS) + hint)
        else:
            opts["profile"] = v
    for key, lo, hi in (("photons", 1, MAX_MC_PHOTONS), ("seed", 0, 2**32 - 1)):
        if key in table:
            v = table[key]
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                problems.append(f"{where}.{key} = {v!r}: must be an integer in {lo} .. {hi}")
            else:
                opts[key] = v
    return rest, opts, problems


_LAYER_KEYS = ("thickness_mm", "eta", "sigma_a", "sigma_s_prime", "sigma_s", "g")
_TOP_KEYS = ("layers", "eta_above", "eta_below")


def _unknown(keys, allowed, where: str, prefix: str) -> list[str]:
    msgs = []
    for k in keys:
        if k not in allowed:
            close = difflib.get_close_matches(k, allowed, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            msgs.append(f"{where}: {prefix}{k}: unknown key{hint}; allowed: {', '.join(allowed)}")
    return msgs


def _number(value: Any, where: str, key: str, unit: str, *, allow_inf: bool = False) -> float:
    if isinstance(value, str) and allow_inf and value.strip().lower() in ("inf", "infinity"):
        return math.inf
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        allowed = 'a number or "inf"' if allow_inf else "a number"
        raise ConfigError(f"{where}: {key} = {value!r}{unit}: must be {allowed}")
    v = float(value)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ConfigError(f"{where}: {key} = {value!r}{unit}: must be finite")
    return v


def _vec3(value: Any, where: str, key: str) -> Vec3:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ConfigError(f"{where}: {key} = {value!r} (1/mm): must be 3 numbers (R, G, B)")
    out = tuple(_number(v, where, key, " (1/mm)") for v in value)
    if any(v < 0 for v in out):
        raise ConfigError(f"{where}: {key} = {_fmt(value)} (1/mm): must be >= 0")
    return out  # type: ignore[return-value]


def _fmt(value) -> str:
    return "[" + ", ".join(f"{v:g}" if isinstance(v, (int, float)) else repr(v) for v in value) + "]"


def _eta(value: Any, where: str, key: str) -> float:
    v = _number(value, where, key, "")
    if v < 1.0:
        raise ConfigError(f"{where}: {key} = {v:g}: must be >= 1 (absolute refractive index)")
    return v


def _parse_layer(tab: Any, where: str, i: int, last: bool) -> tuple[Layer | None, list[str]]:
    """(the layer or None, every problem found in it)."""
    pre = f"layers[{i}]."
    if not isinstance(tab, dict):
        return None, [f"{where}: layers[{i}] = {tab!r}: must be a table"]
    problems = _unknown(tab.keys(), _LAYER_KEYS, where, pre)
    for req in ("thickness_mm", "eta", "sigma_a"):
        if req not in tab:
            problems.append(f"{where}: {pre}{req}: missing (required)")
    if ("sigma_s_prime" in tab) == ("sigma_s" in tab):
        problems.append(f"{where}: {pre}sigma_s_prime / {pre}sigma_s: give exactly one of them"
                        " (sigma_s needs g; sigma_s_prime = sigma_s * (1 - g))")
    d = eta = sa = ss = ssp = None
    if "thickness_mm" in tab:
        d = _collect(problems, _number, tab["thickness_mm"], where, pre + "thickness_mm",
                     " (mm)", allow_inf=True)
        if d is not None and d < 0:
            problems.append(f"{where}: {pre}thickness_mm = {d:g} (mm): must be >= 0 "
                            "(0 means no layer)")
        elif d is not None and math.isinf(d) and not last:
            problems.append(f"{where}: {pre}thickness_mm = inf: only the last layer may be "
                            "semi-infinite")
    if "eta" in tab:
        eta = _collect(problems, _eta, tab["eta"], where, pre + "eta")
    g = _collect(problems, _number, tab.get("g", 0.0), where, pre + "g", "")
    if g is not None and not -1.0 < g < 1.0:
        problems.append(f"{where}: {pre}g = {g:g}: must be in (-1, 1) "
                        "(Henyey-Greenstein mean cosine)")
        g = None
    if "sigma_a" in tab:
        sa = _collect(problems, _vec3, tab["sigma_a"], where, pre + "sigma_a")
    if "sigma_s_prime" in tab:
        ssp = _collect(problems, _vec3, tab["sigma_s_prime"], where, pre + "sigma_s_prime")
    elif "sigma_s" in tab:
        ss = _collect(problems, _vec3, tab["sigma_s"], where, pre + "sigma_s")
        if ss is not None and g is not None:
            ssp = tuple(s * (1.0 - g) for s in ss)
    if sa is not None and ssp is not None:
        for c, (a, s) in enumerate(zip(sa, ssp)):
            if a + s <= 0:
                problems.append(f"{where}: {pre}sigma_a + sigma_s_prime = 0 in channel "
                                f"{'RGB'[c]}: must be > 0 (a layer must absorb or scatter)")
    if problems:
        return None, problems
    return Layer(d, eta, sa, ssp, g), []  # type: ignore[arg-type]


def parse_layer_stack(table: dict, *, where: str) -> LayerStack:
    """Validate a layer table (as read from TOML) into a :class:`LayerStack`.

    Parameters
    ----------
    table : dict
        ``{"layers": [{thickness_mm, eta, sigma_a, sigma_s_prime | sigma_s, g?}, ...],
        "eta_above"?: float, "eta_below"?: float}``; thickness in mm (or ``"inf"``),
        coefficients in 1/mm as three numbers (R, G, B).
    where : str
        Name of the source (file path or scene key) used as the prefix of error messages.

    Returns
    -------
    LayerStack

    Raises
    ------
    ConfigError
        Unknown keys (with a did-you-mean), missing keys, and values breaking a rule
        listed in the module docstring; the message names ``where``, the key, the value
        and the rule, e.g. ``"x.toml: layers[1].sigma_a = [-1, 0, 0] (1/mm): must be >= 0"``.
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: must be a table with [[layers]]")
    # every problem is listed at once, like the rest of the scene validation
    # (docs/hardening.md "The rule")
    problems = _unknown(table.keys(), _TOP_KEYS, where, "")
    layers = table.get("layers")
    parsed: list = []
    if not isinstance(layers, list) or not layers:
        problems.append(f"{where}: layers: missing or empty; give at least one [[layers]] table")
    else:
        for i, t in enumerate(layers):
            layer, bad = _parse_layer(t, where, i, i == len(layers) - 1)
            problems.extend(bad)
            parsed.append(layer)
    eta_above = _collect(problems, _eta, table.get("eta_above", 1.0), where, "eta_above")
    eta_below = _collect(problems, _eta, table.get("eta_below", 1.0), where, "eta_below")
    if parsed and all(l is not None and l.thickness_mm == 0 for l in parsed):
        problems.append(f"{where}: layers: every layer has thickness_mm = 0; "
                        "at least one must be > 0")
    if problems:
        raise ConfigError("\n".join(problems))
    return LayerStack(tuple(parsed), eta_above, eta_below)


def _collect(problems: list, fn, *args, **kw):
    """``fn(*args)``, or None with its ConfigError's message appended to ``problems``."""
    try:
        return fn(*args, **kw)
    except ConfigError as exc:
        problems.append(str(exc))
        return None


def load_layers_toml(path: str | Path) -> LayerStack:
    """Read and validate a layer file (``[[layers]]`` tables); errors name the file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read layer file ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text (UTF-8) file: byte 0x{exc.object[exc.start]:02x} "
                          f"at offset {exc.start} is not UTF-8 (layer files are TOML, which "
                          "is UTF-8)") from None
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse_layer_stack(table, where=str(path))


# ---------------------------------------------------------------------------------------
# Presets.
#
# skin1 / skin2: Jensen, Marschner, Levoy, Hanrahan 2001, "A practical model for subsurface
#   light transport", Table of measured skin (eta = 1.3), 1/mm; docs/science.md section 3.
#
# two_layer: epidermis 0.25 mm over dermis, eta 1.4 (the layered face of docs/science.md
#   section 3), coefficients from the Donner-Jensen 2006 chromophore model ("A spectral
#   BSSRDF for shading human skin", EGSR 2006) with melanin fraction C_m = 0.008 (all
#   eumelanin) in the epidermis and blood fraction C_h = 0.009 (75 % oxygenated) in the
#   dermis, evaluated at one representative wavelength per channel: R 650, G 550, B 450 nm.
#   * Absorption spectra are Jacques's (omlc.org "Optical properties of skin", 1998/2013):
#     eumelanin 6.6e11 * lambda^-3.33 /cm, baseline skin 0.244 + 85.3 exp(-(lambda-154)/66.2)
#     /cm, whole blood (150 g/L Hb) 2.303 * eps * 150 / 64500 /cm with Prahl's molar
#     extinction eps (HbO2/Hb: 650 nm 368/3750, 550 nm 43016/53412, 450 nm 62816/103292
#     cm^-1/M).  Donner-Jensen 2006 print the melanin formula with mm^-1; read that way a
#     C_m = 0.008 epidermis would absorb 10x more than Jacques's own light-skin range, so
#     we keep Jacques's units (/cm) and convert to /mm.
#   * Reduced scattering, both layers: Donner-Jensen 2006,
#     sigma_s'(lambda) = 14.74 lambda^-0.22 + 2.2e11 lambda^-4 (1/mm); its Rayleigh part
#     equals Jacques's 2e12 lambda^-4 /cm, which supports the mm^-1 reading.
#   Results (1/mm):
#     epidermis sigma_a = 0.008*mel + 0.992*base = (0.256, 0.441, 0.893)
#     dermis    sigma_a = 0.009*blood + 0.991*base = (0.035, 0.265, 0.472)
#     sigma_s' = (4.78, 6.08, 9.20)
#   The dermis sigma_a agrees with Jensen 2001 Skin1 (0.032, 0.17, 0.48) to within the
#   spread of measured skin.  g = 0.8: mean cosine of skin, docs/science.md section 2.
#   Dermis thickness: the docs/science.md face used 20 mm; it is optically semi-infinite
#   (sigma_tr >= 0.7 /mm, so e^{-sigma_tr d} < 1e-6), so we write inf.
# ---------------------------------------------------------------------------------------


def _skin_two_layer() -> LayerStack:
    lam = (650.0, 550.0, 450.0)
    eps_oxy = {650.0: 368.0, 550.0: 43016.0, 450.0: 62816.0}
    eps_deoxy = {650.0: 3750.12, 550.0: 53412.0, 450.0: 103292.0}
    mel = [6.6e11 * l ** -3.33 / 10.0 for l in lam]                          # 1/mm
    base = [(0.244 + 85.3 * math.exp(-(l - 154.0) / 66.2)) / 10.0 for l in lam]
    blood = [2.303 * (0.75 * eps_oxy[l] + 0.25 * eps_deoxy[l]) * 150.0 / 64500.0 / 10.0
             for l in lam]
    ssp = tuple(round(14.74 * l ** -0.22 + 2.2e11 * l ** -4, 3) for l in lam)
    epi_a = tuple(round(0.008 * m + 0.992 * b, 4) for m, b in zip(mel, base))
    derm_a = tuple(round(0.009 * h + 0.991 * b, 4) for h, b in zip(blood, base))
    return LayerStack((Layer(0.25, 1.4, epi_a, ssp, 0.8),
                       Layer(math.inf, 1.4, derm_a, ssp, 0.8)), 1.0, 1.0)


PRESETS: dict[str, LayerStack] = {
    # Jensen et al. 2001, measured skin, semi-infinite, eta 1.3 (docs/science.md section 3).
    "skin1": LayerStack((Layer(math.inf, 1.3, (0.032, 0.17, 0.48), (0.74, 0.88, 1.01)),)),
    "skin2": LayerStack((Layer(math.inf, 1.3, (0.013, 0.070, 0.145), (1.09, 1.59, 1.79)),)),
    "two_layer": _skin_two_layer(),
}
