"""OpenCL runtime: device choice, program build from ``cl/``, build cache, kernel timing.

Device choice, in order: the explicit ``spec`` argument (CLI ``--device``), the
``DERMIS_CL_DEVICE`` environment variable, then the default: the PoCL CPU device.
A spec is ``P:D`` (platform and device index, as ``dermis devices`` prints them),
``P`` (first device of platform P), or a case-insensitive substring of the
platform or device name (``pocl``, ``nvidia``, ``cuda``...).

Programs are built from files in ``cl/`` with ``cl/`` on the include path, so
every kernel can ``#include "common.h"``.  A ``#line`` directive makes compiler
messages name the real file, and a failed build raises :class:`KernelBuildError`
with the file, line, ``-D`` options, device and the compiler log.

Running out of memory is :class:`DeviceMemoryError`, a :class:`MemoryError`: an OpenCL
allocation failure (``MEM_OBJECT_ALLOCATION_FAILURE``, ``OUT_OF_RESOURCES``,
``OUT_OF_HOST_MEMORY``, :func:`allocation_failure`) where buffers are created or programs
built, or too little address space left under a ``ulimit -v`` limit for PoCL to compile and
load a kernel (:func:`check_headroom`): PoCL aborts the whole process (SIGABRT, exit 134) when
it cannot map a kernel's library, so the headroom is checked before every program use and
buffer copy instead.  The command line reports a MemoryError in a stage as "out of memory in
stage X" (exit 2).
"""
from __future__ import annotations

import hashlib
import os
import re
import resource
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from .errors import DermisError

__all__ = [
    "ClEnv", "KernelBuildError", "NoOpenCLError", "CL_DIR", "get_env", "list_devices",
    "kernel_sources_hash", "kernel_closure", "event_seconds", "check_device", "to_device",
    "DeviceMemoryError", "allocation_failure", "check_headroom",
]

ENV_VAR = "DERMIS_CL_DEVICE"
CL_DIR = Path(str(resources.files("dermis.cl")))
_INCLUDE_RE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.M)

INSTALL_HINT = (
    "No OpenCL runtime found. dermis needs an OpenCL CPU implementation: install PoCL with\n"
    "  apt-get install pocl-opencl-icd ocl-icd-libopencl1   (Debian/Ubuntu)\n"
    "or run the project's set-up script: bash .ci/setup"
)


class NoOpenCLError(DermisError):
    """No OpenCL platform/device is available, or the requested one does not exist."""


class KernelBuildError(DermisError):
    """An OpenCL program failed to compile; the message names file:line and the log."""


class DeviceMemoryError(MemoryError):
    """The OpenCL device (or the process, for PoCL) has no memory left for a buffer, a
    program or a kernel; the message names what was asked for and the OpenCL error."""


# OpenCL status codes of an allocation that failed (CL/cl.h): pyopencl raises them as
# pyopencl.MemoryError (-4, -6) or pyopencl.RuntimeError (-5), named in the message
_ALLOCATION_FAILURES = {-4: "MEM_OBJECT_ALLOCATION_FAILURE", -5: "OUT_OF_RESOURCES",
                        -6: "OUT_OF_HOST_MEMORY"}


def allocation_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is an OpenCL allocation failure (see :data:`_ALLOCATION_FAILURES`):
    a ``pyopencl.MemoryError``, or a pyopencl error or RuntimeError naming one of the codes."""
    if isinstance(exc, DeviceMemoryError):
        return True
    cl = sys.modules.get("pyopencl")
    is_cl = cl is not None and isinstance(exc, cl.Error)
    if is_cl and isinstance(exc, cl.MemoryError):
        return True
    if not (is_cl or isinstance(exc, RuntimeError)):
        return False
    try:
        code = exc.code if is_cl else None
    except Exception:   # an Error built from a bare message has no status code
        code = None
    return code in _ALLOCATION_FAILURES or any(
        name in str(exc) for name in _ALLOCATION_FAILURES.values())


@contextmanager
def allocating(what: str):
    """Turn an OpenCL allocation failure inside the block into :class:`DeviceMemoryError`
    naming ``what`` (e.g. "a 64.0 MiB buffer on Portable Computing Language / ...")."""
    try:
        yield
    except Exception as exc:
        if isinstance(exc, DeviceMemoryError) or not allocation_failure(exc):
            raise
        raise DeviceMemoryError(f"{what}: the OpenCL device could not allocate it "
                                f"({type(exc).__name__}: {exc})") from exc


# Address space PoCL needs beyond the data to build and load one more kernel: LLVM's code
# generation, the mapped kernel library and its work-group threads (measured on the 2-core
# PoCL 5 machine: a context takes ~380 MiB of address space, a first build ~110 MiB).
POCL_HEADROOM_BYTES = 256 << 20


def _address_space_used() -> int | None:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def check_headroom(nbytes: int, what: str) -> None:
    """Raise :class:`DeviceMemoryError` when the process's address-space limit (``ulimit -v``,
    RLIMIT_AS) leaves less than ``nbytes`` + :data:`POCL_HEADROOM_BYTES`: PoCL aborts the
    process when it cannot map a kernel, so the shortage is reported before it gets there.
    Without such a limit (the usual case) this does nothing."""
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY:
        return
    used = _address_space_used()
    if used is None:
        return
    left = limit - used
    if int(nbytes) + POCL_HEADROOM_BYTES > left:
        need = (f"{_mib(nbytes)} plus " if nbytes else "") + (
            f"{_mib(POCL_HEADROOM_BYTES)} to compile and load kernels")
        raise DeviceMemoryError(f"{what}: {need} are needed, {_mib(max(left, 0))} of the "
                                f"address-space limit (ulimit -v {limit >> 10}) are left")


def _mib(nbytes: int) -> str:
    return f"{nbytes / 2**20:.1f} MiB"


def _cl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise NoOpenCLError(f"pyopencl is not installed ({exc}); run: pip install -e .") from exc
    return cl


def _platforms():
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise NoOpenCLError(INSTALL_HINT + f"\n(pyopencl said: {exc})") from None
    if not platforms:
        raise NoOpenCLError(INSTALL_HINT)
    return platforms


@dataclass(frozen=True)
class DeviceInfo:
    platform_index: int
    device_index: int
    platform: str
    name: str
    type: str
    compute_units: int
    global_mem_mb: int
    fp64: bool
    version: str


def list_devices() -> list[DeviceInfo]:
    """Every OpenCL device on every platform, for ``dermis devices``."""
    cl = _cl()
    out = []
    for pi, p in enumerate(_platforms()):
        try:
            devices = p.get_devices()
        except cl.Error:
            devices = []
        for di, d in enumerate(devices):
            out.append(DeviceInfo(
                pi, di, p.name.strip(), d.name.strip(), cl.device_type.to_string(d.type),
                int(d.max_compute_units), int(d.global_mem_size >> 20),
                bool(d.double_fp_config), d.version.strip()))
    return out


def _pick(spec: str | None):
    cl = _cl()
    platforms = _platforms()
    pairs = [(pi, di, p, d) for pi, p in enumerate(platforms)
             for di, d in enumerate(_safe_devices(p))]
    if not pairs:
        raise NoOpenCLError(INSTALL_HINT + "\n(platforms exist but expose no devices)")
    if spec:
        spec = spec.strip()
        m = re.fullmatch(r"(\d+)(?::(\d+))?", spec)
        if m:
            pi, di = int(m.group(1)), int(m.group(2) or 0)
            for cand in pairs:
                if cand[0] == pi and cand[1] == di:
                    return cand[2], cand[3]
            raise NoOpenCLError(
                f"OpenCL device '{spec}' does not exist; available: "
                + ", ".join(f"{a}:{b} ({d.name.strip()})" for a, b, _, d in pairs)
                + " (see `dermis devices`)")
        low = spec.lower()
        for _, _, p, d in pairs:
            if low in p.name.lower() or low in d.name.lower() or low in p.vendor.lower():
                return p, d
        raise NoOpenCLError(
            f"no OpenCL device matches '{spec}'; available: "
            + ", ".join(f"{a}:{b} {p.name.strip()} / {d.name.strip()}" for a, b, p, d in pairs))
    for _, _, p, d in pairs:  # default: PoCL CPU
        if "portable computing language" in p.name.lower() and d.type & cl.device_type.CPU:
            return p, d
    for _, _, p, d in pairs:
        if d.type & cl.device_type.CPU:
            return p, d
    return pairs[0][2], pairs[0][3]


def _safe_devices(p):
    try:
        return p.get_devices()
    except Exception:  # a broken ICD must not hide the others
        return []


def _resolve_includes(name: str, seen: set[str]) -> list[str]:
    """``name`` and every header it includes (recursively), relative to CL_DIR."""
    if name in seen:
        return []
    seen.add(name)
    path = CL_DIR / name
    if not path.is_file():
        raise KernelBuildError(f"OpenCL source {path} does not exist")
    files = [name]
    for inc in _INCLUDE_RE.findall(path.read_text()):
        files += _resolve_includes(inc, seen)
    return files


def kernel_closure(names) -> list[Path]:
    """The named ``cl/`` files and every header they include (recursively), sorted, deduplicated."""
    seen: set[str] = set()
    for name in names:
        _resolve_includes(name, seen)
    return [CL_DIR / f for f in sorted(seen)]


def kernel_sources_hash(names: tuple[str, ...] | list[str]) -> str:
    """Hash of the named ``cl/`` files and every header they include (program cache keys)."""
    h = hashlib.sha256()
    for path in kernel_closure(names):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@dataclass
class ClEnv:
    """An OpenCL context + profiling queue on one device, with a program cache."""

    context: object
    queue: object
    device: object
    platform: object
    _programs: dict = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def description(self) -> str:
        return f"{self.platform.name.strip()} / {self.device.name.strip()}"

    @property
    def is_pocl(self) -> bool:
        return "portable computing language" in self.platform.name.lower()

    def program(self, name: str, defines: dict | None = None):
        """Build (or fetch from cache) ``cl/<name>`` with ``-D`` defines."""
        cl = _cl()
        defines = dict(sorted((defines or {}).items()))
        opts = [f"-I{CL_DIR}", "-cl-mad-enable"]
        opts += [f"-D{k}={v}" for k, v in defines.items()]
        key = (name, kernel_sources_hash([name]), tuple(opts))
        check_headroom(0, f"OpenCL program {name} on {self.description}")
        with self._lock:
            if key in self._programs:
                return self._programs[key]
            path = CL_DIR / name
            if not path.is_file():
                raise KernelBuildError(f"OpenCL source {path} does not exist")
            src = f'#line 1 "{path}"\n' + path.read_text()
            t0 = time.perf_counter()
            try:
                with allocating(f"building OpenCL program {name} on {self.description}"):
                    prg = cl.Program(self.context, src).build(options=opts)
            except cl.RuntimeError as exc:
                log = str(exc)
                where = _first_error_location(log, path)
                raise KernelBuildError(
                    f"OpenCL build of {where} failed on {self.description}\n"
                    f"options: {' '.join(opts)}\ncompiler log:\n{log.strip()}") from None
            self._programs[key] = prg
            _BUILD_SECONDS[0] += time.perf_counter() - t0
            return prg

    def kernel(self, name: str, kernel_name: str, defines: dict | None = None):
        """A fresh kernel object (its arguments are its own) from a cached program."""
        return _cl().Kernel(self.program(name, defines), kernel_name)


def _first_error_location(log: str, path: Path) -> str:
    # clang prints "FILE:LINE:COL: error: ..."; PoCL 3 prints "error: FILE:LINE:COL: ..."
    for pattern in (r"([^\s:]+\.(?:cl|h)):(\d+):(?:\d+:)?\s*error", r"error:\s*([^\s:]+\.(?:cl|h)):(\d+)"):
        m = re.search(pattern, log)
        if m:
            return f"{m.group(1)}:{m.group(2)}"
    return str(path)


_ENVS: dict[str, ClEnv] = {}


_BUILD_SECONDS = [0.0]   # this process's time in OpenCL program builds (each is done once)


def build_seconds() -> float:
    """Seconds this process has spent building OpenCL programs so far."""
    return _BUILD_SECONDS[0]


def check_device(spec: str | None = None) -> str | None:
    """Validate a device choice up front, before any stage runs: the explicit ``spec``
    (``--device``), else ``$DERMIS_CL_DEVICE``.  Returns the device description, or None
    when neither is set (the default device is found when a stage first needs it).

    Raises :class:`NoOpenCLError` naming where the bad spec came from."""
    source = "--device" if spec else (f"${ENV_VAR}" if os.environ.get(ENV_VAR) else None)
    if source is None:
        return None
    try:
        return get_env(spec).description
    except NoOpenCLError as exc:
        raise NoOpenCLError(f"{source} = {(spec or os.environ[ENV_VAR])!r}: {exc}") from None


def get_env(spec: str | None = None) -> ClEnv:
    """The :class:`ClEnv` for ``spec`` (see module docstring); one per process and device."""
    cl = _cl()
    spec = spec or os.environ.get(ENV_VAR) or None
    platform, device = _pick(spec)
    key = f"{platform.name}|{device.name}|{device.int_ptr}"
    if key not in _ENVS:
        with allocating(f"an OpenCL context on {platform.name.strip()} / {device.name.strip()}"):
            ctx = cl.Context([device])
            queue = cl.CommandQueue(ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
        _ENVS[key] = ClEnv(ctx, queue, device, platform)
    return _ENVS[key]


def event_seconds(events) -> float:
    """Summed device execution time of profiling events, in seconds."""
    total = 0
    for ev in events if isinstance(events, (list, tuple)) else [events]:
        ev.wait()
        total += ev.profile.end - ev.profile.start
    return float(total) * 1e-9


def to_device(env: ClEnv, array: np.ndarray):
    """Copy a contiguous host array to a read-only device buffer.

    A copy, also on CPU devices: a ``USE_HOST_PTR`` buffer would save ~60 ms per 67 MB, but
    pyopencl lets go of the host array when the Python buffer object goes, which can happen
    while a kernel enqueued with it still runs (a temporary buffer passed straight to an
    asynchronous launch); with nodes on two threads the freed memory was reused and one
    BSSRDF image in a few runs differed (tests/test_pipeline.py test09)."""
    cl = _cl()
    array = np.ascontiguousarray(array)
    if not array.nbytes:
        array = np.zeros(4, array.dtype)
    what = f"a {_mib(array.nbytes)} buffer on {env.description}"
    check_headroom(array.nbytes, what)
    with allocating(what):
        return cl.Buffer(env.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                         hostbuf=array)
