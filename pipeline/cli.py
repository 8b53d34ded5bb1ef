"""The ``dermis`` command line.

Exit codes: 0 success, 2 bad input (scene, file, device, locked cache), 1 internal failure.
"""
from __future__ import annotations

import argparse
import errno
import os
import sys
import traceback
from pathlib import Path

import dermis

from .errors import ConfigError, DermisError
from .registry import COMMANDS, command
from .taskpool import task_pool

__all__ = ["main"]


def progress_bars():
    """A progress callback drawing one tqdm bar per running stage (stderr)."""
    from tqdm import tqdm

    bars = {}

    def progress(node, fraction):
        bar = bars.get(node.id)
        if bar is None:
            bar = bars[node.id] = tqdm(total=100, desc=f"{node.id:<14}", leave=False,
                                       file=sys.stderr, bar_format="{desc} {bar} {percentage:3.0f}% {elapsed}",
                                       disable=None)
        bar.n = int(round(100 * min(max(fraction, 0.0), 1.0)))
        bar.refresh()
        if fraction >= 1.0:
            bar.close()
            bars.pop(node.id, None)

    return progress


def _scene(args):
    from .config import load_scene
    return load_scene(args.scene)


def cmd_run(args) -> int:
    from . import api
    scene = _scene(args)
    print(f"scene {scene.path}  cache {api.cache_dir_for(scene, args.cache).resolve()}",
          file=sys.stderr)
    if args.workers < 1:
        raise DermisError(f"--workers {args.workers}: must be >= 1")
    with task_pool(args.workers, args.scheduler) as tasks:
        summary = api.run(scene, cache=args.cache, until=args.until,
                          force=tuple(args.force or ()), device=args.device,
                          progress=None if args.quiet else progress_bars(), jobs=args.jobs,
                          tasks=tasks)
    print(summary.table())
    print(f"outputs in {os.path.join(scene.output.output_dir, scene.scene.name)}")
    return 0


def cmd_status(args) -> int:
    from . import api
    scene = _scene(args)
    summary = api.status(scene, cache=args.cache, until=args.until)
    w = max(len(n.id) for n in summary.nodes)
    for n in summary.nodes:
        why = "; ".join(n.reasons) if n.reasons else ""
        print(f"{n.id:<{w}}  {n.status:<6}  {why}")
    stale = sum(n.status == "stale" for n in summary.nodes)
    print(f"{stale} of {len(summary.nodes)} stages stale")
    return 0


def cmd_clean(args) -> int:
    from . import api
    scene = _scene(args) if args.scene else None
    n = api.clean(cache=args.cache, scene=scene, stage=args.stage)
    print(f"removed {n} cached artifact(s) from {api.cache_dir_for(scene, args.cache).resolve()}")
    return 0


def cmd_devices(args) -> int:
    from . import api
    from .cl import get_env
    default = get_env(args.device)
    for d in api.devices():
        mark = "*" if (d.name == default.device.name.strip()
                       and d.platform == default.platform.name.strip()) else " "
        print(f"{mark} {d.platform_index}:{d.device_index}  {d.platform} / {d.name}  [{d.type}] "
              f"compute units {d.compute_units}, memory {d.global_mem_mb} MiB, "
              f"fp64 {'yes' if d.fp64 else 'no'}, {d.version}")
    print("* = device used (choose with --device P:D or a name, or $DERMIS_CL_DEVICE)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .registry import STAGE_NAMES

    p = argparse.ArgumentParser(prog="dermis", description=(
        "Render faces with classic skin models side by side and measure them."))
    p.add_argument("--version", action="version", version=f"dermis {dermis.__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    def jobs(sp):
        sp.add_argument("-j", "--jobs", default=None, metavar="N",
                        help="nodes run at once on threads (or $DERMIS_JOBS; default 2); "
                             "the results are the same for any N")

    def common(sp, scene_optional=True):
        sp.add_argument("scene", nargs="?" if scene_optional else None, default=None,
                        help="scene TOML (default: the embedded scene, scenes/default.toml)")
        sp.add_argument("--cache", default=None, help="cache directory (or $DERMIS_CACHE)")

    r = sub.add_parser("run", help="build what is stale for a scene")
    common(r)
    jobs(r)
    r.add_argument("--until", choices=STAGE_NAMES, metavar="STAGE",
                   help="build only what STAGE needs: " + ", ".join(STAGE_NAMES))
    r.add_argument("--force", action="append", metavar="STAGE", help="recompute STAGE (repeatable)")
    r.add_argument("--device", default=None, help="OpenCL device: P:D, P, or a name substring")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    r.add_argument("--workers", type=int, default=1, metavar="N",
                   help="Dask worker processes for the tasks of a node (the reference's "
                        "tiles; default 1: this process); the results are the same for any N")
    r.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run those tasks on the workers of an existing Dask scheduler")
    r.set_defaults(func=cmd_run)

    s = sub.add_parser("status", help="what is cached, what is stale and why")
    common(s)
    s.add_argument("--until", choices=STAGE_NAMES, metavar="STAGE")
    s.set_defaults(func=cmd_status)

    c = sub.add_parser("clean", help="delete cached artifacts")
    common(c)
    c.add_argument("--stage", default=None, help="only this stage's artifacts")
    c.set_defaults(func=cmd_clean)

    d = sub.add_parser("devices", help="list OpenCL platforms and devices")
    d.add_argument("--device", default=None)
    d.set_defaults(func=cmd_devices)

    for name in COMMANDS:  # subcommands of the physics packages (e.g. ``profile``)
        command(name).add_parser(sub)
    return p


# File-system faults the user can fix (exit 2, not a traceback): a full disk or quota, a
# read-only or unwritable folder, a file where a folder should be, a file-size limit.
FS_FAULTS = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
             errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
             errno.EPERM: "operation not permitted", errno.ENOTDIR: "not a folder",
             errno.EISDIR: "is a folder", errno.EEXIST: "already exists",
             errno.EFBIG: "file too large (file-size limit)",
             errno.ENAMETOOLONG: "file name too long"}


def user_fault(exc: BaseException) -> str | None:
    """The message for a failure the user can fix though it is not a DermisError: a file-system
    fault or running out of memory (possibly inside a stage); None for a real bug."""
    where = ""
    node = getattr(exc, "node_id", None)
    cause = exc.__cause__ if node is not None and exc.__cause__ is not None else exc
    if node is not None:
        where = f" in stage {node}"
    if isinstance(cause, MemoryError):
        return (f"out of memory{where}: the scene needs more memory than this machine has; "
                "lower camera.width/height, bake.resolution, bssrdf.point_density or "
                "mesh.high_triangles (finished stages stay cached)")
    if isinstance(cause, OSError) and cause.errno in FS_FAULTS:
        name = cause.filename or ""
        return (f"{FS_FAULTS[cause.errno]}{where}" + (f": {name}" if name else "")
                + "; free space or fix the folder's permissions (or choose another --cache / "
                "output_dir) and run again: cache entries are written whole or not at all, so "
                "nothing was corrupted")
    return None


def check_text_file(path) -> None:
    """Refuse a scene file that is not UTF-8 text (TOML is UTF-8), naming the file and the
    first byte that is not: the commands' own readers raised a bare UnicodeDecodeError.  A
    file that is missing or unreadable is left to them."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text (UTF-8) file: byte 0x{data[exc.start]:02x} at "
                          f"offset {exc.start} is not UTF-8 (scene files are TOML, which is "
                          "UTF-8)") from None


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # argparse: usage errors exit 2, --help exits 0
            return int(exc.code or 0)
        if getattr(args, "scene", None):
            check_text_file(args.scene)
        return int(args.func(args) or 0)
    except DermisError as exc:
        print(f"dermis: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("dermis: interrupted; finished stages stay cached, the unfinished one was discarded",
              file=sys.stderr)
        return 130
    except Exception as exc:  # internal failure: show the traceback, exit 1
        fault = user_fault(exc)
        if fault is not None:
            print(f"dermis: error: {fault}", file=sys.stderr)
            return 2
        tb = getattr(exc, "tb", None) or traceback.format_exc()
        print(tb, file=sys.stderr)
        print(f"dermis: internal error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
