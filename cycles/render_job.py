"""The Cycles render process: ``python -m dermis.cycles.render_job FOLDER`` (one job), or
``python -m dermis.cycles.render_job --serve FD IDLE_S`` (jobs one after another).

``bpy`` is one Blender per process (its scene, its threads, its numpy build), so Cycles
renders in processes of its own, started by :mod:`dermis.cycles.job`: the pipeline's
process never imports ``bpy``, a crash in Blender is a failed node with Blender's output,
and a render's threads are exactly the job's.  The folder holds ``job.json`` (what to
render) and ``arrays.npz`` (dermis's arrays); the process writes ``result.npz`` and
``result.json`` there.  A serving process (:func:`serve`) keeps the head mesh it built,
and with it Blender's BVH of it (persistent data), for the next job of the same mesh: the
other images of a head then cost their renders only.  Two kinds of job:

* ``head``: the scene (:mod:`dermis.cycles.scene_build`) rendered as two halves of
  independent seeds, a pilot and then as many samples as the target noise needs
  (:mod:`dermis.cycles.sampling`); result: the halves, their mean, the coverage, the passes.
* ``slab``: a flat semi-infinite slab (a box far larger and deeper than the light travels in
  it) seen straight down by an orthographic camera, once per entry of ``renders``: lit by a
  uniform sky of radiance 1 (the normal-view radiance is then the slab's reflectance at
  normal incidence, by reciprocity), or by a sun straight down through a round hole in a
  black screen, the camera looking down the hole's centre, once per hole radius R (it sees
  the light that entered within R of it: the exit profile's cumulative F(R), by
  translation invariance and reciprocity); result: the mean RGB per render
  (:mod:`dermis.cycles.slab`).
"""
from __future__ import annotations

import importlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from dermis.cycles import sampling, scene_build as sb

__all__ = ["main", "render_head", "render_slabs", "ROWS"]

ROWS = 4   # Blender's smallest image side: the slab renders are 4 x 4 pixels


def _material(obj, m: dict, texture=None) -> None:
    sb.skin_material(obj, method=m["method"], base_colour=m.get("base_colour"),
                     base_texture=texture, radius=m.get("radius", (1.0, 1.0, 1.0)),
                     ior=m.get("ior", 1.4), roughness=m.get("roughness", 0.3),
                     anisotropy=m.get("anisotropy", 0.0), subsurface_ior=m.get("subsurface_ior"),
                     volume=m.get("volume"))


MESH_ARRAYS = ("vertices", "faces", "normals", "uv", "uv_faces")


class _Kept:
    """The head mesh a serving process keeps between its jobs (:func:`serve`): the arrays it
    was built from, its scene and object."""
    arrays: dict | None = None
    scene = None
    obj = None


def _same_mesh(arrays) -> bool:
    if _Kept.arrays is None:
        return False
    for k in MESH_ARRAYS:
        a, b = _Kept.arrays.get(k), (arrays[k] if k in arrays.files else None)
        if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
            return False
    return True


def _clear_but_mesh(scene, obj) -> None:
    """Everything of the previous job but the head mesh: camera, lights, world, material and
    images go (the next job adds its own); Blender's render data of the mesh (its BVH) stays
    with persistent data."""
    import bpy
    for ob in list(scene.collection.objects):
        if ob != obj:
            bpy.data.objects.remove(ob, do_unlink=True)
    obj.data.materials.clear()
    for coll in (bpy.data.lights, bpy.data.cameras, bpy.data.worlds, bpy.data.materials):
        for d in list(coll):
            coll.remove(d)
    for img in list(bpy.data.images):
        if img.type != "RENDER_RESULT":
            bpy.data.images.remove(img)


def _head_mesh(job: dict, arrays, w: int, h: int):
    """(scene, head object, reused): the kept mesh when this process built the same arrays
    before (only its job's other parts cleared), else a new scene."""
    if _same_mesh(arrays):
        _clear_but_mesh(_Kept.scene, _Kept.obj)
        sb.settings(_Kept.scene, width=w, height=h, threads=job["threads"])
        return _Kept.scene, _Kept.obj, True
    get = (lambda k: arrays[k] if k in arrays.files else None)
    scene = sb.reset()
    _Kept.arrays = None
    sb.settings(scene, width=w, height=h, threads=job["threads"])
    obj = sb.add_mesh(scene, arrays["vertices"], arrays["faces"], normals=get("normals"),
                      uv=get("uv"), uv_faces=get("uv_faces"))
    _Kept.arrays = {k: (np.array(arrays[k]) if k in arrays.files else None)
                    for k in MESH_ARRAYS}
    _Kept.scene, _Kept.obj = scene, obj
    return scene, obj, False


def render_head(job: dict, arrays, folder: Path) -> dict:
    """Build the head scene (or reuse the mesh this process built: :func:`serve`) and render
    it to the job's target noise (module docstring)."""
    t0 = time.perf_counter()
    w, h = int(job["width"]), int(job["height"])
    get = (lambda k: arrays[k] if k in arrays.files else None)
    scene, obj, reused = _head_mesh(job, arrays, w, h)
    cam = job["camera"]
    sb.add_camera(scene, position=cam["position"], forward=cam["forward"], up=cam["up"],
                  fov_deg=cam["fov_deg"], width=w, height=h)
    target = np.asarray(arrays["vertices"], np.float64).mean(axis=0)
    sb.add_lights(scene, [l for l in job["lights"] if l["type"] != "environment"],
                  target=target)
    env = [l for l in job["lights"] if l["type"] == "environment"]
    sb.add_world(scene, get("environment"),
                 rotation_deg=float(env[0].get("rotation_deg", 0.0)) if env else 0.0)
    _material(obj, job["material"], get("base_texture"))
    t_build = time.perf_counter() - t0

    s = job["sampling"]
    halves, seed = sampling.Halves(), int(job["seed"])
    scratch = str(folder / "pass.exr")
    coverage = None
    spp, k, noise = int(s["pilot_spp"]), 0, None
    t_render = 0.0
    while spp > 0:
        t1 = time.perf_counter()
        a = sb.render_pixels(scene, seed=2 * (seed + k), spp=spp, scratch=scratch)
        b = sb.render_pixels(scene, seed=2 * (seed + k) + 1, spp=spp, scratch=scratch)
        dt = time.perf_counter() - t1
        t_render += dt
        if coverage is None:
            coverage = np.minimum(a[..., 3], b[..., 3]) > 0.5
        halves.add(a[..., :3], b[..., :3], spp, seeds=[2 * (seed + k), 2 * (seed + k) + 1],
                   seconds=dt)
        A, B = halves.halves()
        noise = sampling.block_noise(A, B, coverage, int(s["block"]))
        halves.passes[-1]["noise"] = noise
        need = sampling.samples_for(noise, halves.spp, float(s["target_noise"]),
                                    max_spp=int(s["max_spp"]))
        k += 1
        # one more pass when the target is 5 % off (the pilot's own noise estimate is noisy)
        spp = need - halves.spp if (noise > 1.05 * s["target_noise"] and k < 3) else 0
    A, B = halves.halves()
    np.savez(folder / "result.npz", half_a=A.astype(np.float32), half_b=B.astype(np.float32),
             coverage=coverage)
    return {"spp_per_half": halves.spp, "spp": 2 * halves.spp, "noise": noise,
            "passes": halves.passes, "build_seconds": t_build, "render_seconds": t_render,
            "faces": int(len(arrays["faces"])), "mesh_reused": reused}


def _occluder(scene, *, height: float, side: float):
    """A black plane at ``height`` with a round hole at the origin, transparent inside the
    hole and to camera rays, opaque black to every other ray; returns the hole radius's
    value socket."""
    import bpy
    v = np.array([[-side, -side, 0.0], [side, -side, 0.0], [side, side, 0.0],
                  [-side, side, 0.0]])
    obj = sb.add_mesh(scene, v, np.array([[0, 1, 2], [0, 2, 3]]), name="occluder")
    obj.location = (0.0, 0.0, height)   # object coordinates: z = 0 on the screen
    mat = bpy.data.materials.new("occluder")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    black = nt.nodes.new("ShaderNodeBsdfDiffuse")
    black.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    clear = nt.nodes.new("ShaderNodeBsdfTransparent")
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(black.outputs[0], mix.inputs[1])
    nt.links.new(clear.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], out.inputs["Surface"])
    coord = nt.nodes.new("ShaderNodeTexCoord")
    length = nt.nodes.new("ShaderNodeVectorMath")
    length.operation = "LENGTH"
    nt.links.new(coord.outputs["Object"], length.inputs[0])
    radius = nt.nodes.new("ShaderNodeValue")
    inside = nt.nodes.new("ShaderNodeMath")
    inside.operation = "LESS_THAN"
    nt.links.new(length.outputs["Value"], inside.inputs[0])
    nt.links.new(radius.outputs[0], inside.inputs[1])
    path = nt.nodes.new("ShaderNodeLightPath")
    either = nt.nodes.new("ShaderNodeMath")
    either.operation = "MAXIMUM"
    nt.links.new(inside.outputs[0], either.inputs[0])
    nt.links.new(path.outputs["Is Camera Ray"], either.inputs[1])
    nt.links.new(either.outputs[0], mix.inputs[0])
    obj.data.materials.append(mat)
    return radius.outputs[0]


def _slab(scene, side: float):
    v = np.array([[-side, -side, -side], [side, -side, -side], [side, side, -side],
                  [-side, side, -side], [-side, -side, 0.0], [side, -side, 0.0],
                  [side, side, 0.0], [-side, side, 0.0]])
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    obj = sb.add_mesh(scene, v, f, name="slab")
    obj.data.polygons.foreach_set("use_smooth", np.zeros(len(f), bool))
    return obj


def render_slabs(job: dict, folder: Path) -> dict:
    """The flat-slab renders of ``job["renders"]`` (module docstring): per entry, the mean
    RGB of the image, one row per hole radius (``holes``) or one row (``sky``)."""
    import bpy
    t0 = time.perf_counter()
    out, log = {}, []
    scratch = str(folder / "pass.exr")
    _Kept.arrays = None      # each slab render starts from an empty Blender
    for i, r in enumerate(job["renders"]):
        scene = sb.reset()
        sb.settings(scene, width=ROWS, height=ROWS, threads=job["threads"])
        # the hole's radius changes between renders: no render data kept from one to the next
        scene.render.use_persistent_data = False
        side = float(r["side"])
        obj = _slab(scene, side)
        _material(obj, r["material"])
        t1 = time.perf_counter()
        if r["light"] == "holes":
            radii = [float(x) for x in r["radii"]]
            # a window smaller than the smallest hole, looking at its centre
            sb.add_camera(scene, position=(0.0, 0.0, 4.0 * radii[-1] + 1.0), forward=(0, 0, -1),
                          up=(0, 1, 0), fov_deg=0.0, width=ROWS, height=ROWS,
                          orthographic_scale=float(r["window"]))
            sb.add_world(scene, None)
            sb.add_lights(scene, [{"type": "directional", "name": "sun",
                                   "intensity": [1.0, 1.0, 1.0], "direction": [0, 0, 1]}],
                          target=(0, 0, 0))
            hole = _occluder(scene, height=2.0 * radii[-1] + 0.5, side=side)
            rows = []
            for R in radii:
                hole.default_value = R
                img = sb.render_pixels(scene, seed=int(r["seed"]), spp=int(r["spp"]),
                                       scratch=scratch)
                rows.append(img[..., :3].reshape(-1, 3).mean(axis=0))
            out[f"image{i}"] = np.asarray(rows, np.float32)
        else:       # a uniform sky of radiance 1
            sb.add_camera(scene, position=(0.0, 0.0, 10.0), forward=(0, 0, -1), up=(0, 1, 0),
                          fov_deg=0.0, width=ROWS, height=ROWS,
                          orthographic_scale=float(r["window"]))
            world = bpy.data.worlds.new("sky")
            scene.world = world
            world.use_nodes = True
            bg = world.node_tree.nodes["Background"]
            bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
            bg.inputs["Strength"].default_value = 1.0
            img = sb.render_pixels(scene, seed=int(r["seed"]), spp=int(r["spp"]), scratch=scratch)
            out[f"image{i}"] = img[..., :3].reshape(-1, 3).mean(axis=0)[None].astype(np.float32)
        log.append({"seconds": time.perf_counter() - t1})
    np.savez(folder / "result.npz", **out)
    return {"renders": log, "seconds": time.perf_counter() - t0}


def run_folder(folder: Path) -> None:
    """The job in ``folder``: its result written there (module docstring)."""
    import bpy
    job = json.loads((folder / "job.json").read_text())
    t0, c0 = time.perf_counter(), time.process_time()
    if job["kind"] == "head":
        with np.load(folder / "arrays.npz") as arrays:
            result = render_head(job, arrays, folder)
    else:
        result = render_slabs(job, folder)
    result["process_seconds"] = time.perf_counter() - t0
    result["cpu_seconds"] = time.process_time() - c0     # every thread's, this job's
    result["blender"] = bpy.app.version_string
    (folder / "result.json").write_text(json.dumps(result))
    try:
        os.remove(folder / "pass.exr")
    except OSError:
        pass


def serve(done_fd: int, idle_s: float) -> int:
    """Render the jobs whose folders arrive one per line on stdin, in this one process (the
    head mesh and its BVH kept between jobs of the same mesh: :func:`render_head`); after
    each, write its folder's name and a newline to the file descriptor ``done_fd``.  Each
    job's console output (Blender's included) goes to its folder's ``blender.log``, a
    failure's traceback to ``error.txt``.  Exits at the end of stdin or after ``idle_s``
    seconds without a job."""
    import select
    import traceback
    importlib.import_module("bpy")   # Blender's start, once (fails here without bpy)
    done = os.fdopen(done_fd, "w")
    saved_out, saved_err = os.dup(1), os.dup(2)
    while True:
        ready, _, _ = select.select([sys.stdin], [], [], idle_s)
        line = sys.stdin.readline() if ready else ""
        if not line.strip():
            return 0
        folder = Path(line.strip())
        sys.stdout.flush()
        sys.stderr.flush()
        log = os.open(folder / "blender.log", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(log, 1)
        os.dup2(log, 2)
        try:
            run_folder(folder)
        except Exception:
            (folder / "error.txt").write_text(traceback.format_exc())
            _Kept.arrays = None      # the next job starts from an empty Blender
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved_out, 1)
            os.dup2(saved_err, 2)
            os.close(log)
        done.write(f"{folder}\n")
        done.flush()


def main(argv=None) -> int:
    args = list(argv or sys.argv[1:])
    if args[0] == "--serve":
        return serve(int(args[1]), float(args[2]))
    importlib.import_module("bpy")   # fails here, with Blender's message, without bpy
    run_folder(Path(args[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
