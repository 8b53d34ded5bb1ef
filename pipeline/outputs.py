"""The output folder ``output_dir/<scene name>/``: what a run writes there, and how it replaces
the previous run's outputs whole.

A run's outputs are the file artifacts of its nodes (``<stage folder>/<file>``) and
``run.json``; the entries a run owns there are ``run.json`` and every stage's output folder
(:func:`owned_entries`).  Anything else in the folder (a sweep's ``sweep/``, a user's notes)
is kept from run to run.

The export (:func:`export`) never shows a mixture of two runs' outputs:

1. the new outputs are assembled in a sibling folder ``output_dir/.<scene>.export-<owner>``
   (``<owner>`` = host, process id and a run id), invisible in ``output_dir/<scene>/``;
2. the entries the run does not own are moved into it, one ``rename`` each: for those few
   milliseconds they are missing from the folder, whose outputs are still wholly the old;
3. the two folders are exchanged in one step (``renameat2(RENAME_EXCHANGE)``, Linux 3.15+,
   on the file systems that have it: ext4, xfs, btrfs, tmpfs): at one instant
   ``output_dir/<scene>`` is the old folder, at the next the new one.  Where the exchange is
   not available the old folder is renamed aside (``.<scene>.old-<owner>``) and the new one
   into place: between those two renames ``output_dir/<scene>`` is absent, never mixed;
4. the old folder, now ``.<scene>.export-<owner>`` (or ``.old-``), is deleted; a reader that
   has opened a file of it keeps reading it (POSIX), and a shell whose working folder was the
   old one must ``cd`` again.

A run killed at any step leaves the folder wholly old or wholly new (or, after a kill between
the two renames of the fallback, absent), and its sibling folders behind.  Every export (and
every run, before its first stage) first removes the leftovers of this scene whose owner is
gone (a process of this host that no longer exists, or an export of this process that is
over), after moving back any entry it does not own that a kill left in them.  Leftovers of
processes on other hosts sharing the folder are left alone.
"""
from __future__ import annotations

import ctypes
import errno
import json
import os
import re
import shutil
import threading
import uuid
from pathlib import Path

from .config import Scene
from .errors import DermisError
from .registry import STAGE_NAMES, stage
from .store import Store, owner_gone, owner_token

__all__ = ["output_folder", "owned_entries", "export", "remove_leftovers"]

_LEFTOVER = re.compile(r"^\.(?P<scene>.+)\.(?P<kind>export|old)-(?P<host>[^-]+)-(?P<pid>\d+)-"
                       r"(?P<run>[0-9a-f]{32})$")
# leftovers of earlier versions inside the folder itself: assembled outputs, or the owned
# entries of an older run moved aside (never anything a run does not own)
_LEGACY = re.compile(r"^\.(export|old)-[0-9a-f]{32}$")
_ACTIVE: set[str] = set()           # run ids of this process's exports in progress
_ACTIVE_LOCK = threading.Lock()


def output_folder(scene: Scene) -> Path:
    """``output_dir/<scene.name>/``, created, with the leftovers of killed exports removed;
    refused (exit 2, naming ``output.output_dir``) when it cannot be written.  Checked before
    any stage runs."""
    base = Path(scene.output.output_dir)
    out = base / scene.scene.name
    key = f"output.output_dir = {json.dumps(scene.output.output_dir)}"
    for p in (base, out):
        if p.exists() and not p.is_dir():
            raise DermisError(f"{scene.path}: {key}: {p} is a file, not a folder; choose "
                              "another output_dir (or remove the file)")
    probe = out / f".write-check-{uuid.uuid4().hex}"
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe.mkdir()
        probe.rmdir()
    except OSError as exc:
        raise DermisError(f"{scene.path}: {key}: outputs cannot be written to {out}: "
                          f"{exc.strerror or exc}; choose another output_dir") from None
    remove_leftovers(_real(out))
    return out


def _real(out: Path) -> Path:
    """The folder itself where ``out`` (or a folder above it) is a symbolic link: the swap
    replaces the folder the link points to, never the link."""
    return Path(os.path.realpath(out))


def owned_entries() -> set[str]:
    """The entries of ``output_dir/<scene>/`` a run writes (and replaces): run.json and the
    stage output folders.  Anything else there (a sweep's folder, a user's notes) is kept."""
    return {"run.json"} | {getattr(stage(n), "OUTPUT_FOLDER", n) for n in STAGE_NAMES}


def export(scene: Scene, store: Store, summary) -> Path:
    """Copy the file artifacts of ``summary``'s nodes to ``output_dir/<scene>/<stage folder>/``
    and write run.json beside them, replacing the previous run's outputs whole (module
    docstring).  Exceptions other than OSError (which becomes a :class:`DermisError`) pass
    through; any exception removes the new folder, except those that stop the process
    (KeyboardInterrupt, SystemExit): like a kill, they leave it to the next export."""
    out = _real(output_folder(scene))
    run_id = uuid.uuid4().hex
    owner = f"{owner_token()}-{run_id}"
    new = out.parent / f".{out.name}.export-{owner}"
    with _ACTIVE_LOCK:
        _ACTIVE.add(run_id)
    try:
        _assemble(new, scene, store, summary)
        _carry_over(out, new)
        old = _swap(new, out, out.parent / f".{out.name}.old-{owner}")
        _remove(old, out)
    except OSError as exc:
        _remove(new, out)
        raise DermisError(f"{scene.path}: output.output_dir: writing the outputs to {out} "
                          f"failed: {exc.strerror or exc} ({exc.filename or out}); the cache "
                          "is intact: free space or choose another output_dir and run again") \
            from None
    except Exception:
        _remove(new, out)
        raise
    finally:
        with _ACTIVE_LOCK:
            _ACTIVE.discard(run_id)
    return out


def _assemble(new: Path, scene: Scene, store: Store, summary) -> None:
    """The run's outputs in the fresh folder ``new``: each node's listed files (inside its
    cache entry, :meth:`Store.output_files`) under its stage folder, and run.json."""
    new.mkdir()
    files = []
    for rep in summary.nodes:
        folder = (getattr(stage(rep.stage), "OUTPUT_FOLDER", rep.stage)
                  if rep.stage in STAGE_NAMES else rep.stage)
        for src in store.output_files(rep.id, rep.key):
            (new / folder).mkdir(exist_ok=True)
            shutil.copy2(src, new / folder / src.name)
            files.append(f"{folder}/{src.name}")
    (new / "run.json").write_text(json.dumps({
        "scene": scene.path, "cache": str(store.root), "files": sorted(files),
        "warnings": list(getattr(summary, "warnings", [])),
        "nodes": [{"id": r.id, "status": r.status, "seconds": r.seconds,
                   "kernel_seconds": r.kernel_seconds, "key": r.key, "reasons": r.reasons}
                  for r in summary.nodes]}, indent=1))


def _carry_over(out: Path, new: Path) -> None:
    """Move the entries of ``out`` that no run owns into ``new`` (one rename each)."""
    owned = owned_entries()
    for entry in sorted(out.iterdir()) if out.is_dir() else []:
        if entry.name not in owned and not _is_temporary(entry.name):
            os.rename(entry, new / entry.name)


def _is_temporary(name: str) -> bool:
    return bool(_LEGACY.match(name)) or name.startswith(".write-check-")


def _swap(new: Path, out: Path, aside: Path) -> Path:
    """Put ``new`` in the place of ``out``; return where the old folder went (``new``'s
    name after an exchange, ``aside`` after the two-rename fallback)."""
    if _exchange(new, out):
        return new
    try:
        os.rename(out, aside)
    except FileNotFoundError:       # removed meanwhile: nothing to replace
        pass
    os.rename(new, out)
    return aside


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Exchange two paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``); False where the
    C library, the kernel or the file system cannot, or ``b`` does not exist."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOENT):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _remove(folder: Path, out: Path) -> None:
    """Delete a sibling folder of ``out``, first moving back into ``out`` any entry that no
    run owns (a kill between the carry-over and the swap leaves them there).  An entry that
    ``out`` has again meanwhile is moved back as ``<name>.kept-<hex>``: nothing of the user's
    is ever deleted."""
    if not folder.is_dir():
        return
    owned = owned_entries()
    for entry in sorted(folder.iterdir()):
        if entry.name in owned or _is_temporary(entry.name):
            continue
        out.mkdir(parents=True, exist_ok=True)
        dest = out / entry.name
        if dest.exists() or dest.is_symlink():
            dest = out / f"{entry.name}.kept-{uuid.uuid4().hex[:8]}"
        os.rename(entry, dest)
    shutil.rmtree(folder, ignore_errors=True)


def remove_leftovers(out: Path) -> list[Path]:
    """Remove the sibling folders that killed exports of this scene left (module docstring),
    moving back the entries they hold that no run owns; return the removed paths.  (Leftovers
    of earlier versions inside the folder, ``.export-<hex>`` and ``.old-<hex>``, go with the
    old folder at the next swap: :func:`_carry_over` leaves them behind.)"""
    removed = []
    try:
        siblings = sorted(out.parent.iterdir())
    except OSError:
        return removed
    for entry in siblings:
        m = _LEFTOVER.match(entry.name)
        if m is None or m["scene"] != out.name or not entry.is_dir() or entry.is_symlink():
            continue
        if m["host"] == owner_token().partition("-")[0] and int(m["pid"]) == os.getpid():
            with _ACTIVE_LOCK:
                gone = m["run"] not in _ACTIVE     # this process: once that export is over
        else:
            gone = owner_gone(m["host"], int(m["pid"]))
        if not gone:
            continue
        try:
            _remove(entry, out)
        except OSError:         # not ours to remove (permissions): left, never fatal
            continue
        removed.append(entry)
    return removed
