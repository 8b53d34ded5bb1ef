"""Rules that relate scene values to each other, checked at load before any stage runs.

The schema (``pipeline/config.py``) checks each value on its own: type, range, unit.  The
rules here need more than one value, or what a consumer of the value can represent: a
direction whose length squares outside double precision, a camera whose up vector is
parallel to its view, a name that must become a file name, the reference's size against the
camera's, an environment map's header.  (What a rendered model needs of the scene, its
module declares: ``Model.check``.)  Each returns the problems it finds as messages naming
the file, the key, the value and the rule.  :func:`scene_warnings` lists what validates but
makes a run useless (nothing rendered, a black lighting condition).
"""
from __future__ import annotations

import math
from pathlib import Path

from .registry import model

__all__ = ["scene_warnings", "fmt", "direction_problem", "plain_name_problem", "check_camera", "check_reference",
           "check_environment_file", "DIRECTION_LENGTH"]


def fmt(value) -> str:
    """A scene value as the scene file writes it (strings quoted, arrays in brackets)."""
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(fmt(v) for v in value) + "]"
    return repr(value)


# Directions (camera.up, lights[].direction) are normalised in double precision
# (rendering/camera.py camera_vectors, lighting/emitters.py): a length outside these
# bounds squares to below the smallest normal double (2.2e-308) or beyond the largest.
DIRECTION_LENGTH = (1e-150, 1e150)


def direction_problem(v) -> str | None:
    """Why vector ``v`` cannot be normalised to a direction (None if it can)."""
    if not any(v):
        return "must not be zero"
    n = math.hypot(*v)
    lo, hi = DIRECTION_LENGTH
    if not lo <= n <= hi:
        return (f"has length {n:.3g}; a direction's length must be in [{lo:g}, {hi:g}] (its "
                "square must stay within double precision); only its direction matters, so "
                "scale it")
    return None


def plain_name_problem(value: str, extra: str = "") -> str | None:
    """Why ``value`` cannot be used as one file-name component (None if it can)."""
    if not value.strip():
        return "must not be empty"
    if value in (".", "..") or value.startswith("."):
        return "must not start with '.'"
    bad = [c for c in "/\\" + extra if c in value]
    if bad:
        return f"must be a plain name without {' or '.join(repr(c) for c in bad)}"
    if any(ord(c) < 32 or ord(c) == 127 for c in value):
        return "must not contain control characters"
    if len(value.encode()) > 100:
        return "must be at most 100 bytes long"
    return None


def check_camera(camera, where: str, key: str = "camera") -> list[str]:
    """The problems of a CameraConfig (at ``key``: ``camera`` or a view's) the renderer would
    otherwise find only after the mesh stages."""
    out = []
    pos, look, up = camera.position, camera.look_at, camera.up
    fwd = [b - a for a, b in zip(pos, look)]
    nf = math.hypot(*fwd)
    why = direction_problem(up)
    if not nf > 0:
        out.append(f"{where}: {key}.look_at = {fmt(look)}: must differ from "
                   f"{key}.position = {fmt(pos)}")
    elif why:
        out.append(f"{where}: {key}.up = {fmt(up)}: {why}")
    else:   # unit vectors: the cross product of any two valid vectors stays finite
        nu = math.hypot(*up)
        f = [x / nf for x in fwd]
        u = [x / nu for x in up]
        cross = (f[1] * u[2] - f[2] * u[1], f[2] * u[0] - f[0] * u[2],
                 f[0] * u[1] - f[1] * u[0])
        if not math.hypot(*cross) > 1e-9:
            out.append(f"{where}: {key}.up = {fmt(up)}: must not be parallel to the "
                       f"view direction {key}.look_at - {key}.position = "
                       f"{fmt(tuple(fwd))}")
    return out


def reference_size(camera, ref) -> tuple[int, int]:
    """The reference's pixels: ``ref.width`` x ``ref.height`` when given, else the camera's
    size divided by the smallest factor that divides both sides and leaves at most 100
    pixels across (the default 800-pixel camera: 100 x 100)."""
    if ref.width and ref.height:
        return int(ref.width), int(ref.height)
    w, h = int(camera.width), int(camera.height)
    f = next(f for f in range(1, max(w, h) + 1) if w % f == 0 and h % f == 0
             and max(w, h) // f <= 100 or f == math.gcd(w, h))
    return w // f, h // f


def check_reference(ref, given: set, camera, labels, where: str) -> list[str]:
    """The ``[reference]`` keys a scene gives (``given``; ``ref`` the ReferenceConfig, ``labels``
    the lighting conditions), checked at load whether the reference is on or off."""
    out = []
    if (ref.width == 0) != (ref.height == 0):
        out.append(f"{where}: reference.width x height = {ref.width} x {ref.height}: give both, "
                   "or neither (0: chosen from the camera)")
    elif camera is not None and given & {"width", "height"} and ref.width:
        if camera.width % ref.width or camera.height % ref.height:
            out.append(f"{where}: reference.width x height = {ref.width} x {ref.height}: must "
                       f"divide the camera's {camera.width} x {camera.height} (a reference "
                       "pixel is a block of camera pixels)")
        elif camera.width // ref.width != camera.height // ref.height:
            out.append(f"{where}: reference.width x height = {ref.width} x {ref.height}: must "
                       f"keep the camera's aspect ({camera.width} x {camera.height})")
    if ref.min_spp > ref.max_spp:
        out.append(f"{where}: reference.min_spp = {ref.min_spp} exceeds reference.max_spp = "
                   f"{ref.max_spp}: every head pixel gets min_spp samples per half-buffer, "
                   "none more than max_spp")
    if labels is not None and "lights" in given:
        for label in ref.lights:
            if label not in labels:
                out.append(f"{where}: reference.lights: {fmt(label)} is not a "
                           f"lighting condition of [render] lights ({', '.join(labels)})")
    return out


def check_environment_file(path: Path, where: str, key: str, value: str) -> list[str]:
    """Header check of an environment map file (the pixels are read by the stages)."""
    try:
        import OpenImageIO as oiio   # heavy: imported only for a scene with a map file
    except ImportError:  # pragma: no cover - a dependency
        return []
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        reason = oiio.geterror().strip() or "not an image format OpenImageIO reads"
        return [f"{where}: {key} = {fmt(value)}: cannot be read as an image "
                f"({reason}); give a lat-long HDR or EXR file"]
    try:
        spec = inp.spec()
        if spec.width < 2 or spec.height < 1:
            return [f"{where}: {key} = {fmt(value)}: the image is {spec.width} x "
                    f"{spec.height} pixels; a lat-long map needs at least 2 x 1"]
    finally:
        inp.close()
    return []


def scene_warnings(scene) -> list[str]:
    """Settings that validate but make a run useless (it would render nothing, or black)."""
    where = scene.path
    out = []
    r = scene.render
    if not r.models:
        out.append(f"{where}: render.models = []: nothing is rendered (only the meshes are "
                   "prepared)")
    elif not r.geometries:
        out.append(f"{where}: render.geometries = []: nothing is rendered (only the meshes are "
                   "prepared)")
    for label, lights in scene.light_groups():
        dark = [l for l in lights if not any(l.intensity if l.type != "environment"
                                             else (l.scale,))]
        if r.models and r.geometries and len(dark) == len(lights):
            keys = ", ".join(f"lights.{l.name}." + ("scale = 0.0" if l.type == "environment"
                                                    else f"intensity = {fmt(l.intensity)}")
                             for l in dark)
            out.append(f"{where}: lighting condition {fmt(label)} emits no light ({keys}); "
                       "its renders will be black")
    own = getattr(scene.optics, "profile", None)
    readers: dict = {}      # layer-profile model -> the rendered models that read it
    for name in r.models:
        m = model(name)
        if m.profiles and m.exitance is None:    # an own exitance: another image
            readers.setdefault(m.profile or own, []).append(name)
    for profile, names in readers.items():
        if len(names) > 1:
            out.append(f"{where}: render.models has {' and '.join(names)}, but optics.profile = "
                       f"{fmt(profile)} makes them the same image (drop optics.profile to "
                       "compare the multipole with the Monte Carlo profile)")
    return out
