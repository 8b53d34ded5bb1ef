"""Mitsuba 3 itself: whether it is installed, and which variant of it runs here.

Mitsuba 3 (a dependency of dermis) renders the path-traced ground truth
(docs/ground-truth.md); it is imported only when a reference is made, and a machine where it
cannot run still renders every model (the reference is then skipped with its reason).

Variant: :func:`load_mitsuba` picks ``cuda_ad_rgb`` where a CUDA device answers, else
``llvm_ad_rgb`` where libLLVM is found (Debian's ``libllvm19``; ``DRJIT_LIBLLVM_PATH`` is set
to it when unset) and its JIT works on this CPU (checked in a child process, since a failing
LLVM aborts the process), else Mitsuba counts as unavailable.  ``scalar_rgb`` is not offered:
the scene export and readback use Dr.Jit arrays of many lanes
(:func:`dermis.groundtruth.passes.pixel_hits`, the wavefront renders), which the scalar
variant lacks, and one path at a time would take hours.
"""
from __future__ import annotations


import functools
import glob
import importlib.util
import os
import subprocess
import sys
import threading

from dermis.pipeline.errors import ConfigError, DermisError

__all__ = ["MitsubaUnavailable", "load_mitsuba", "mitsuba_missing_reason", "VARIANTS",
           "INSTALL_HINT", "exclusive"]

VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")
INSTALL_HINT = ("bash .ci/setup, or pip install mitsuba drjit (dermis's dependencies); "
                "without a CUDA device also apt-get install libllvm19 (the llvm_ad_rgb variant)")


class MitsubaUnavailable(DermisError):
    """Mitsuba 3 is not installed (or no variant loads): the reference stage cannot run."""


_STATE: dict = {}


def mitsuba_missing_reason() -> str | None:
    """None if ``import mitsuba`` works, else one sentence saying what to install."""
    try:
        if importlib.util.find_spec("mitsuba") is None or importlib.util.find_spec("drjit") is None:
            return f"Mitsuba 3 is not installed: {INSTALL_HINT}"
    except (ImportError, ValueError):
        return f"Mitsuba 3 is not installed: {INSTALL_HINT}"
    return None


def _find_libllvm() -> str | None:
    pats = ["/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
            "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*"]
    found = sorted({p for pat in pats for p in glob.glob(pat)}, reverse=True)
    # drjit needs LLVM >= 11; prefer the newest (names sort by version)
    return found[0] if found else None


# One import and variant choice at a time: two reference nodes running at once (-j 2) imported
# Mitsuba concurrently and one saw a half-initialised module (no ``variants``).
_LOAD_LOCK = threading.RLock()


# Mitsuba's JIT state is not safe for two Python threads rendering at once: a reference node
# and a causes node at -j 2 failed with "jit_registry_id(...): pointer is not registered".  A
# node runs its Mitsuba work holding this lock (Mitsuba itself already uses every core).
_RENDER_LOCK = threading.RLock()


def exclusive(fn):
    """``fn`` run while no other thread of this process uses Mitsuba (a stage's ``run``)."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        with _RENDER_LOCK:
            return fn(*args, **kwargs)
    return run


def load_mitsuba(variant: str = "auto"):
    """Import Mitsuba and set a variant; returns the ``mitsuba`` module (``.variant()`` says which).

    ``variant = "auto"`` tries :data:`VARIANTS` in order and keeps the first that renders a
    one-pixel test scene.  Raises :class:`MitsubaUnavailable` with the install command.
    Thread-safe: two nodes of a run may ask at once (the first import is not).
    """
    with _LOAD_LOCK:
        return _load_mitsuba(variant)


def _load_mitsuba(variant: str):
    reason = mitsuba_missing_reason()
    if reason:
        raise MitsubaUnavailable(reason)
    if "DRJIT_LIBLLVM_PATH" not in os.environ and "drjit" not in _STATE:
        lib = _find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    # heavy dependency: imported only when a reference is made, once it is known present
    importlib.import_module("drjit")   # before mitsuba, with the libLLVM path set above
    import mitsuba as mi
    _STATE["drjit"] = True
    if variant != "auto":
        if variant not in mi.variants():
            raise ConfigError(f"reference.variant = {variant!r}: not one of this Mitsuba's "
                              f"variants ({', '.join(mi.variants())})")
        broken = _llvm_jit_fails(variant) if variant.startswith("llvm") else None
        if broken:
            raise MitsubaUnavailable(f"reference.variant = {variant!r}: {broken}")
        mi.set_variant(variant)
        return mi
    if _STATE.get("auto"):
        mi.set_variant(_STATE["auto"])
        return mi
    errors = []
    for v in VARIANTS:
        if v not in mi.variants():
            continue
        if v.startswith("cuda") and not _has_backend("CUDA"):
            errors.append(f"{v}: no CUDA device")
            continue
        if v.startswith("llvm"):
            broken = _llvm_jit_fails(v)
            if broken:
                errors.append(f"{v}: {broken}")
                continue
        try:
            mi.set_variant(v)
            scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"}, "sensor": {
                "type": "perspective", "film": {"type": "hdrfilm", "width": 1, "height": 1}}})
            mi.render(scene, spp=1)
            _STATE["auto"] = v
            return mi
        except Exception as exc:  # no CUDA device, no libLLVM: try the next one
            errors.append(f"{v}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}")
    raise MitsubaUnavailable("no Mitsuba variant could render (" + "; ".join(errors) + "); "
                             + INSTALL_HINT)


# Run in a child process before the LLVM variant is used here: an LLVM that cannot compile
# Dr.Jit's code for this CPU aborts the whole process ("LLVM ERROR: Cannot select ... fmaximum":
# Debian 12's libLLVM-15 on an AVX-512 host, where drjit's dr.maximum became llvm.maximum;
# libllvm19 compiles it).  The child evaluates that operation and renders one pixel.
_LLVM_PROBE = """
import drjit as dr, mitsuba as mi
mi.set_variant({variant!r})
x = dr.maximum(dr.arange(mi.Float, 64) - 3.0, 0.0) + dr.minimum(dr.arange(mi.Float, 64), 2.0)
dr.eval(x)
mi.render(mi.load_dict({{"type": "scene", "integrator": {{"type": "path"}}, "sensor": {{
    "type": "perspective", "film": {{"type": "hdrfilm", "width": 1, "height": 1}}}}}}), spp=1)
"""


def _llvm_jit_fails(variant: str) -> str | None:
    """None if ``variant`` compiles and runs in a child process, else why not (one line);
    probed once per process and libLLVM."""
    key = ("llvm_probe", variant, os.environ.get("DRJIT_LIBLLVM_PATH"))
    if key not in _STATE:
        _STATE[key] = _probe_llvm(variant)
    return _STATE[key]


def _probe_llvm(variant: str) -> str | None:
    try:
        child = subprocess.run([sys.executable, "-c", _LLVM_PROBE.format(variant=variant)],
                               capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"the LLVM JIT probe did not finish ({type(exc).__name__})"
    if child.returncode == 0:
        return None
    lines = [ln for ln in child.stderr.splitlines() if ln.strip()]
    first = next((ln for ln in lines if "ERROR" in ln or "Error" in ln), lines[-1] if lines else "")
    return (f"the LLVM JIT fails on this CPU with {os.environ.get('DRJIT_LIBLLVM_PATH', 'libLLVM')}"
            f" (exit {child.returncode}: {first[:160]}); apt-get install libllvm19")


def _has_backend(name: str) -> bool:
    import drjit as dr  # optional dependency, present once load_mitsuba got this far
    try:
        return bool(dr.has_backend(getattr(dr.JitBackend, name)))
    except Exception:
        return False
