"""Outputs and the cache under hostile use: EXR precision, cache entries that name files
outside themselves or lie about their data, kills during the export, OpenCL allocation
failures, ``--force`` of a stage a run would not run, dim lights.  docs/hardening.md
("Outputs and the cache") lists the cases.

The quick scene (scenes/quick.toml) shrunk to a 2,000-triangle head, one BRDF model, one point
light, one geometry and 32 x 32 pixels, with its own cache; runs are in-process
(``dermis.pipeline.cli.main`` or ``api.run``) so imports and OpenCL builds are paid once.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline import api, outputs
from dermis.pipeline.cli import main
from dermis.pipeline.config import load_scene
from dermis.pipeline.errors import DermisError
from dermis.pipeline.imageio import ImageRangeWarning, read_image, write_exr
from dermis.pipeline.store import Store

sys.path.insert(0, str(Path(__file__).parent))
from scene_toml import scene_file  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RENDER = "render-lafortune-point-high"
EXR = "lafortune-point-high.exr"
POINT = {"name": "point", "type": "point", "position": [350.0, 450.0, 600.0],
         "intensity": [4.0e5, 4.0e5, 4.0e5]}

@pytest.fixture(scope="module")
def warm(tmp_path_factory):
    """A cache holding the tiny scene (shared; tests that damage it work on a copy)."""
    root = tmp_path_factory.mktemp("outputs")
    cache = root / "cache"
    assert main(["run", str(scene_file(root)), "--cache", str(cache), "-q"]) == 0
    return cache


def _copy(cache: Path, dest: Path) -> Path:
    shutil.copytree(cache, dest, ignore=shutil.ignore_patterns(".lock", ".tmp"))
    return dest


def _run(scene: Path, cache: Path, capsys, *extra) -> tuple[int, str]:
    rc = main(["run", str(scene), "--cache", str(cache), "-q", *extra])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


def _entry(cache: Path, node: str, scene: Path) -> Path:
    """The entry of ``node`` that ``scene`` uses."""
    rep = {n.id: n for n in api.status(load_scene(scene), cache=cache).nodes}[node]
    return cache / node / rep.key


def _edit_meta(entry: Path, edit) -> None:
    meta = json.loads((entry / "meta.json").read_text())
    (entry / "meta.json").write_text(json.dumps(edit(meta)))


# --------------------------------------------------------------------------- 1. EXR precision
@pytest.mark.parametrize("intensity", [1e12, 1e-3])
def test01_exr_holds_the_rendered_float32_data(intensity, warm, tmp_path, capsys):
    """Half-float EXRs wrote +Inf for most head pixels at 1e12 and all zeros at 1e-3 while the
    cached float32 data were finite and non-zero: the EXR now holds the data exactly."""
    scene = scene_file(tmp_path, {"lights": [dict(POINT, intensity=[intensity] * 3)]})
    rc, err = _run(scene, warm, capsys)
    assert rc == 0 and "warning" not in err, err
    img = read_image(tmp_path / "out" / "quick" / "render" / EXR)   # refuses NaN / Inf
    with np.load(_entry(warm, RENDER, scene) / "data.npz") as data:
        linear = data["linear"]
    assert img.max() > 0 and np.array_equal(img, linear)


def test02_unrepresentable_values_warn_naming_the_image_and_range(tmp_path):
    """Values float32 cannot hold are written as float32 stores them, with a warning naming
    the file and the value range; in a run the warning becomes a notice (from any thread)."""
    values = np.full((4, 4, 3), 0.5)
    values[0, 0] = 1e40
    values[1, 1] = 1e-50
    notices = []
    with api._image_warnings(notices.append) as texts:
        worker = threading.Thread(target=write_exr, args=(tmp_path / "odd.exr", values))
        worker.start()
        worker.join()
    assert len(texts) == 1 and notices == [f"warning: {texts[0]}"]
    for part in ("odd.exr", "3 values beyond the float32 maximum", "stored as Inf",
                 "3 non-zero values below", "stored as 0", "from 1e-50 to 1e+40"):
        assert part in texts[0], (part, texts[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", ImageRangeWarning)
        write_exr(tmp_path / "fine.exr", np.full((4, 4, 3), 1e-30))    # float32 holds it
        with pytest.raises(ImageRangeWarning, match="NaN or Inf"):
            write_exr(tmp_path / "nan.exr", np.full((4, 4, 3), np.nan, np.float32))


def test03_a_light_too_dim_for_float32_warns(warm, tmp_path, capsys):
    """A light so dim that every pixel rounds to 0 in float32: the all-zero image (and EXR)
    gets the dark-render warning, in run.json too (a dim light at 1e-3 does not: test01)."""
    scene = scene_file(tmp_path, {"lights": [dict(POINT, intensity=[1e-40] * 3)]})
    rc, err = _run(scene, warm, capsys)
    assert rc == 0
    assert f"{RENDER}: the image is black" in err and "rounds to 0 in float32" in err
    img = read_image(tmp_path / "out" / "quick" / "render" / EXR)
    assert not img.any()
    run = json.loads((tmp_path / "out" / "quick" / "run.json").read_text())
    assert any("rounds to 0 in float32" in w for w in run["warnings"])


# --------------------------------------------------------------------------- 2. damaged entries
X = b"not an output"                 # the file ../../../x reaches from an entry
X_SUM = hashlib.sha256(X).hexdigest()
OUTSIDE = {  # id: (node, edit of its meta.json)
    "files_parent": (RENDER, lambda m: {**m, "files": m["files"] + ["../../../x"]}),
    "files_absolute": (RENDER, lambda m: {**m, "files": m["files"] + ["/etc/hostname"]}),
    "checksums_parent": (RENDER, lambda m: {**m, "files": ["../../../x"],
                                            "checksums": {**m["checksums"], "../../../x": X_SUM},
                                            "sizes": {**m["sizes"], "../../../x": len(X)}}),
    "meta_list": ("mesh_high", lambda m: []),
    "meta_null": ("mesh_high", lambda m: None),
    "files_not_a_list": (RENDER, lambda m: {**m, "files": {"a": 1}}),
}


@pytest.mark.parametrize("case", sorted(OUTSIDE))
def test04_entry_naming_files_outside_itself_or_not_an_object_is_rebuilt(case, warm, tmp_path,
                                                                        capsys):
    """An entry's meta.json that names a file outside the entry (the export copied it out of
    the output folder), or is not an object (`dermis status` and `run` failed with
    AttributeError, forever): corrupted in `status`, rebuilt with one notice by `run`, and
    nothing leaves output_dir/<scene>/."""
    node, edit = OUTSIDE[case]
    c = _copy(warm, tmp_path / "a" / "b" / "c")
    (tmp_path / "a" / "b" / "x").write_bytes(X)           # c/<node>/<key>/../../../x
    scene = scene_file(tmp_path)
    _edit_meta(_entry(c, node, scene), edit)
    assert main(["status", str(scene), "--cache", str(c)]) == 0
    status = capsys.readouterr().out
    assert f"{node}" in status and "corrupted" in status
    rc, err = _run(scene, c, capsys)
    assert rc == 0, err
    notices = [line for line in err.splitlines() if "rebuilding" in line]
    assert len(notices) == 1 and node in notices[0]
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == ["quick"]
    assert not [p for p in out.rglob("*") if p.name in ("x", "hostname")]
    rc, err = _run(scene, c, capsys)
    assert rc == 0 and "rebuilding" not in err                 # healed


@pytest.mark.parametrize("node, extra", [("mesh_high", ("--force", "render")), (RENDER, ())])
def test05_entry_with_empty_checksums_and_its_data_deleted_is_rebuilt(node, extra, warm,
                                                                     tmp_path, capsys):
    """Empty checksums and sizes and the data deleted read as cached, then FileNotFoundError
    (when a stage read it: the forced render reads mesh_high): an entry that held an
    artifact must record both of its files."""
    c = _copy(warm, tmp_path / "c")
    scene = scene_file(tmp_path)
    entry = _entry(c, node, scene)
    (entry / "data.npz").unlink()
    _edit_meta(entry, lambda m: {**m, "checksums": {}, "sizes": {}, "files": []})
    assert main(["status", str(scene), "--cache", str(c)]) == 0
    assert "corrupted" in capsys.readouterr().out
    rc, err = _run(scene, c, capsys, *extra)
    assert rc == 0, err
    assert len([line for line in err.splitlines() if "rebuilding" in line]) == 1
    assert (entry / "data.npz").is_file()


def test06_unrecorded_data_file_and_old_entries(warm, tmp_path):
    """A data file the entry does not record is damage; an entry written before entries said
    whether they held an artifact is valid when it records data, damaged when it records
    none."""
    c = _copy(warm, tmp_path / "c")
    store = Store(c)
    entry = _entry(c, "mesh_high", scene_file(tmp_path))
    key = entry.name
    (entry / "stray.bin").write_bytes(b"x")
    assert "stray.bin is not recorded" in store.verify("mesh_high", key)
    (entry / "stray.bin").unlink()
    _edit_meta(entry, lambda m: {k: v for k, v in m.items() if k != "artifact"})
    assert store.verify("mesh_high", key) is None
    _edit_meta(entry, lambda m: {**m, "checksums": {}, "sizes": {}})
    for name in ("data.npz", "fields.json"):
        (entry / name).unlink()
    assert "records no data files" in store.verify("mesh_high", key)


# --------------------------------------------------------------------------- 3. the export
class Killed(BaseException):
    """A simulated kill: not an Exception, so nothing cleans up after it."""


def _snapshot(folder: Path) -> dict | None:
    """The run's outputs in ``folder``: path -> bytes (None: the folder is absent)."""
    if not folder.is_dir():
        return None
    owned = outputs.owned_entries()
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.relative_to(folder).parts[0] in owned}


def _kill_after(monkeypatch, name: str, nth: int = 1):
    """Make the ``nth`` call of ``outputs.<name>`` (or of os.rename / shutil.copy2 in the
    export) raise Killed once it has returned; ``rmtree``: delete one file of the folder,
    then raise (a kill half-way through deleting the old folder)."""
    if name == "rmtree":
        def partial(path, *a, **k):
            first = next((p for p in sorted(Path(path).rglob("*")) if p.is_file()), None)
            if first is not None:
                first.unlink()
            raise Killed(name)
        monkeypatch.setattr(shutil, "rmtree", partial)
        return
    target = {"rename": os, "copy2": shutil}.get(name, outputs)
    real = getattr(target, name)
    calls = []

    def wrapped(*a, **k):
        result = real(*a, **k)
        calls.append(1)
        if len(calls) == nth:
            raise Killed(f"{name} #{nth}")
        return result

    monkeypatch.setattr(target, name, wrapped)


# after: assembling, its first copy, the carry-over, its first rename (of two entries), the
# swap, removing the old folder, half-way through deleting it; the fallback's first rename
# (the old folder aside, the new not yet in place)
KILLS = [("_assemble", 1), ("copy2", 1), ("_carry_over", 1), ("rename", 1), ("_swap", 1),
         ("_remove", 1), ("rmtree", 1)]


@pytest.mark.parametrize("exchange", [True, False], ids=["exchange", "two_renames"])
def test07_a_kill_at_any_step_of_the_export_leaves_wholly_old_or_new_outputs(exchange, warm,
                                                                             tmp_path,
                                                                             monkeypatch):
    """A kill during the export left `.export-*` and `.old-*` folders that no later run
    removed, and in 1 of 6 kills during the per-entry swap new images beside the old
    render/ and run.json.  At every step now: the folder is wholly old or wholly new (absent
    only between the two renames of the fallback), and the next run removes the leftovers and
    keeps the user's entries."""
    dir_left = {"name": "dir_left", "type": "directional", "direction": [-0.6, 0.3, 0.75],
                "intensity": [0.6, 0.6, 0.6]}
    old_scene = load_scene(scene_file(tmp_path, {"render": {"lights": ["point", "dir_left"]},
                                                 "lights": [POINT, dir_left]}, "a.toml"))
    new_scene = load_scene(scene_file(tmp_path, {}, "b.toml"))
    out = tmp_path / "out" / "quick"
    new_summary = api.run(new_scene, cache=warm, export=False)
    api.run(new_scene, cache=warm)
    new = _snapshot(out)
    api.run(old_scene, cache=warm)
    api.run(old_scene, cache=warm)                        # all cached, as in the loop below
    old = _snapshot(out)
    assert old != new and any("dir_left" in p for p in old)
    kills = KILLS
    exchanged = []
    if exchange:                  # renameat2 must be what swaps here (ext4, tmpfs, ...)
        real_exchange = outputs._exchange
        monkeypatch.setattr(outputs, "_exchange",
                            lambda a, b: exchanged.append(real_exchange(a, b)) or exchanged[-1])
    else:
        monkeypatch.setattr(outputs, "_exchange", lambda a, b: False)
        kills = KILLS + [("rename", 3)]
    store = Store(warm)
    for name, nth in kills:
        api.run(old_scene, cache=warm)                    # back to the old outputs
        (out / "sweep").mkdir(exist_ok=True)              # not a run's: kept throughout
        (out / "sweep" / "keep.txt").write_text("mine")
        (out / "notes.txt").write_text("notes")
        with monkeypatch.context() as m:
            _kill_after(m, name, nth)
            with pytest.raises(Killed):
                outputs.export(new_scene, store, new_summary)
        state = _snapshot(out)
        allowed = [old, new] + ([None] if (name, nth) == ("rename", 3) else [])
        assert state in allowed, (name, nth, sorted(state or {}))
        api.run(new_scene, cache=warm)                    # the next run
        assert _snapshot(out) == new, (name, nth)
        assert (out / "sweep" / "keep.txt").read_text() == "mine", (name, nth)
        assert (out / "notes.txt").read_text() == "notes", (name, nth)
        assert sorted(p.name for p in out.parent.iterdir()) == ["quick"], (name, nth)
        assert not [p for p in out.iterdir() if p.name.startswith(".")], (name, nth)
    assert all(exchanged) and len(exchanged) > len(kills) if exchange else not exchanged


def test08_leftovers_of_dead_processes_and_old_versions_are_removed(warm, tmp_path):
    """Leftovers named for a process of this host that is gone, and the `.export-<hex>` /
    `.old-<hex>` folders of earlier versions, are removed by the next run (the user's entries
    in them moved back); those of a live process or of another host are kept."""
    from dermis.pipeline.store import owner_token
    scene = load_scene(scene_file(tmp_path))
    out = tmp_path / "out" / "quick"
    api.run(scene, cache=warm)
    host = owner_token().partition("-")[0]
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    hexes = iter(f"{i:032x}" for i in range(10))
    gone = [out.parent / f".quick.export-{host}-{dead}-{next(hexes)}",
            out.parent / f".quick.old-{host}-{dead}-{next(hexes)}",
            out / f".export-{next(hexes)}", out / f".old-{next(hexes)}"]
    kept = [out.parent / f".quick.export-{host}-1-{next(hexes)}",          # pid 1 lives
            out.parent / f".quick.export-otherhost-{dead}-{next(hexes)}",
            out.parent / f".other.export-{host}-{dead}-{next(hexes)}"]     # another scene
    for d in gone + kept:
        (d / "render").mkdir(parents=True)
    (gone[0] / "sweep").mkdir()
    (gone[0] / "sweep" / "keep.txt").write_text("mine")
    api.run(scene, cache=warm)
    assert [d for d in gone if d.exists()] == []
    assert all(d.is_dir() for d in kept)
    assert (out / "sweep" / "keep.txt").read_text() == "mine"


# --------------------------------------------------------------------------- 4. memory
def _cl_error(kind: str, code: int, routine: str):
    import pyopencl as cl
    return getattr(cl, kind)(cl._cl._ErrorRecord("", code, routine))


ALLOCATION_FAILURES = {
    "mem_object_allocation_failure": ("MemoryError", -4, "clCreateBuffer"),
    "out_of_resources": ("RuntimeError", -5, "clEnqueueNDRangeKernel"),
    "out_of_host_memory": ("MemoryError", -6, "clCreateBuffer"),
}


@pytest.mark.parametrize("case", sorted(ALLOCATION_FAILURES))
def test09_opencl_allocation_failure_is_the_out_of_memory_error(case, warm, tmp_path, capsys,
                                                                monkeypatch):
    """Under `ulimit -v 2000000` PoCL aborted (exit 134) instead of the documented
    out-of-memory message: an OpenCL allocation failure where buffers are created (to_device
    or a stage's own cl.Buffer) is the out-of-memory error, exit 2 naming the stage."""
    import pyopencl as cl

    from dermis.pipeline.cl import DeviceMemoryError, get_env, to_device
    kind, code, routine = ALLOCATION_FAILURES[case]

    def fail(*a, **k):
        raise _cl_error(kind, code, routine)

    monkeypatch.setattr(cl, "Buffer", fail)
    with pytest.raises(DeviceMemoryError) as info:
        to_device(get_env(), np.zeros(1 << 20, np.float32))
    assert isinstance(info.value, MemoryError)
    assert "4.0 MiB buffer" in str(info.value) and cl.status_code.to_string(code) in str(
        info.value)
    rc, err = _run(scene_file(tmp_path), _copy(warm, tmp_path / "c"), capsys, "--force",
                   "render")
    assert rc == 2 and f"out of memory in stage {RENDER}" in err, err


def test10_too_little_address_space_is_refused_before_pocl_aborts(monkeypatch):
    """PoCL aborts the process when it cannot map a kernel's library: under an address-space
    limit (ulimit -v) with too little left, the buffer copy or program use is refused with
    the out-of-memory error instead, naming the limit."""
    import resource

    from dermis.pipeline import cl as dcl
    env = dcl.get_env()
    used = dcl._address_space_used()
    limit = used + dcl.POCL_HEADROOM_BYTES + (8 << 20)
    monkeypatch.setattr(dcl.resource, "getrlimit",
                        lambda which: (limit, limit) if which == resource.RLIMIT_AS
                        else resource.getrlimit(which))
    dcl.to_device(env, np.zeros(1 << 10, np.float32))              # fits
    with pytest.raises(dcl.DeviceMemoryError, match="ulimit -v"):
        dcl.to_device(env, np.zeros(64 << 20, np.uint8))
    monkeypatch.setattr(dcl.resource, "getrlimit", lambda which: (used, used))
    with pytest.raises(dcl.DeviceMemoryError, match="program shade.cl"):
        env.program("shade.cl")


def test11_no_thread_for_a_stage_is_the_out_of_memory_error(warm, tmp_path, capsys,
                                                            monkeypatch):
    """`RuntimeError: can't start new thread` inside a stage (its stack did not fit under
    `ulimit -v`) gave exit 1 with a traceback: it is the out-of-memory error."""
    from dermis.pipeline import graph

    def no_thread(self, inputs, ctx):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(graph.Node, "call", no_thread)
    rc, err = _run(scene_file(tmp_path), _copy(warm, tmp_path / "c"), capsys, "--force",
                   "mesh_high")
    assert rc == 2 and "out of memory in stage mesh_high" in err, err


# --------------------------------------------------------------------------- 5. --force
def test12_force_of_a_stage_the_run_would_not_run_is_refused(warm, tmp_path, capsys):
    """`--force bssrdf` without the BSSRDF exited 0 doing nothing; `--until mesh_high --force
    render` did not run render and cut the output folder to run.json.  Both are refused at
    the start (exit 2) naming the flag, the stage and why; the outputs are untouched."""
    scene = scene_file(tmp_path)
    assert _run(scene, warm, capsys)[0] == 0
    out = tmp_path / "out" / "quick"
    before = _snapshot(out)
    cases = {("--force", "bssrdf"): ["--force bssrdf", "no bssrdf stage", "its stages:"],
             ("--until", "mesh_high", "--force", "render"): [
                 "--force render", "--until mesh_high does not run render"],
             ("--force", "render-hk93-point-high"): [
                 "--force render-hk93-point-high", "no node", RENDER]}
    for extra, expect in cases.items():
        rc, err = _run(scene, warm, capsys, *extra)
        assert rc == 2, (extra, err)
        for text in expect:
            assert text in err, (text, err)
    assert _snapshot(out) == before
    with pytest.raises(DermisError, match="--force bssrdf"):
        api.run(load_scene(scene), cache=warm, force=("bssrdf",))
    rc, err = _run(scene, warm, capsys, "--until", "render", "--force", "mesh_high")
    assert rc == 0                                        # upstream of --until: runs
