"""A model's BRDF evaluated on the OpenCL device for arrays of direction pairs: its
``<name>_eval`` kernel (``Model.kernel``), for the tests and benchmarks that check the kernels
against closed forms and the float64 references (``tests/brdf_reference.py``).

Conventions: local shading frame with z along the shading normal, ``wo`` and ``wi`` unit
vectors pointing away from the surface, f excludes the cosine, RGB linear.
"""
from __future__ import annotations

import numpy as np

from dermis.models.model import Model
from dermis.pipeline.cl import get_env, to_device
from dermis.pipeline.errors import ConfigError

__all__ = ["evaluate"]


def _directions(v, name: str) -> np.ndarray:
    a = np.asarray(v)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ConfigError(f"{name}: must be an (N, 3) array of directions, got shape {a.shape}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: contains NaN or Inf")
    return a


def evaluate(model: Model, wo, wi, params=None, *, albedo=None, env=None) -> np.ndarray:
    """Evaluate a model's BRDF on the OpenCL device for N direction pairs.

    Parameters
    ----------
    model : Model with a ``kernel`` (e.g. ``models.lafortune.MODEL``)
    wo, wi : (N, 3) float arrays
        Unit directions in the local shading frame (z = normal), both pointing away from the
        surface.  Directions on or below the horizon give f = 0.
    params : an instance of ``model.params``, or None for the defaults
    albedo : (N, 3) or (3,) floats, optional
        Models with an ``albedo`` (Lafortune): linear-RGB albedo per pair, replacing that
        parameter (rho_d), which is the default.
    env : pipeline.cl.ClEnv, optional
        OpenCL environment; default ``pipeline.cl.get_env()``.

    Returns
    -------
    (N, 3) float32 ndarray
        f(wo, wi) in 1/sr per RGB channel (cosine not included).

    Raises
    ------
    ConfigError
        A model without a kernel, parameters of the wrong type, or malformed
        direction/albedo arrays.
    """
    if model.kernel is None:
        raise ConfigError(f"model {model.name!r} has no eval kernel")
    params = model.checked(params, f"params for model {model.name!r}")
    wo = _directions(wo, "wo")
    wi = _directions(wi, "wi")
    if wo.shape != wi.shape:
        raise ConfigError(f"wo and wi must have the same shape, got {wo.shape} and {wi.shape}")
    n = wo.shape[0]
    args = [wo, wi]
    if model.albedo is not None:
        alb = getattr(params, model.albedo) if albedo is None else albedo
        alb = np.asarray(alb, dtype=np.float32)
        if alb.shape == (3,):
            alb = np.broadcast_to(alb, (n, 3))
        if alb.shape != (n, 3):
            raise ConfigError(f"albedo: must have shape (3,) or ({n}, 3), got {alb.shape}")
        if not np.all(np.isfinite(alb)):
            raise ConfigError("albedo: contains NaN or Inf")
        args.append(np.ascontiguousarray(alb))
    elif albedo is not None:
        raise ConfigError(f"albedo: model {model.name!r} reads no albedo")
    out = np.zeros((n, 3), dtype=np.float32)
    if n == 0:
        return out

    import pyopencl as cl  # optional until a kernel runs (pipeline/cl.py NoOpenCLError)
    env = env or get_env()
    kernel = cl.Kernel(env.program(model.kernel), f"{model.name}_eval")
    bufs = [to_device(env, a) for a in args] + [to_device(env, params.pack())]
    out_buf = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
    kernel(env.queue, (n,), None, *bufs, out_buf, np.int32(n))
    cl.enqueue_copy(env.queue, out, out_buf)
    return out
