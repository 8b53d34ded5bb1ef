"""A dermis scene as a Blender Cycles scene, built with ``bpy`` from dermis's own arrays.

Runs inside the render process (:mod:`dermis.cycles.render_job`), never in the pipeline's:
``bpy`` is a process-wide singleton.  No file format sits between dermis and Cycles: the mesh
is made from dermis's vertices, faces, normals (Blender's own where they agree) and
per-corner UVs (``foreach_set``), so no
importer turns axes or welds vertices, and Cycles sees the same triangles as Mitsuba.
The conventions (docs/cycles.md "Units and conventions", each measured there):

* lengths: one Blender unit = 1 mm (unit system NONE); the subsurface radii are in mm;
* camera: pinhole at dermis's position and orientation, ``angle`` across the shorter image
  side (``sensor_fit``), box pixel filter one pixel wide, film transparent (misses are 0);
* point light of intensity I (W/sr): Cycles point power P = 4 pi I, radius 0;
* disc of on-axis intensity I (radiance I / (pi r^2)): a DISK area light of size 2 r and
  power P = pi I, emitting one-sided towards the mesh (dermis's disc emits from both faces;
  the far face lights nothing the camera sees, as in the Mitsuba export);
* directional light of irradiance E: a SUN of strength E, angle 0 (an environment map's sun:
  its angular diameter, :mod:`dermis.cycles.environment`);
* environment: the world's colour read from dermis's lat-long radiance map by dermis's own
  direction -> pixel rule (nearest pixel, ``lighting/environment.py``), importance-sampled;
* every setting that would spoil a comparison is set: no denoising, no adaptive sampling, no
  clamping, no glossy filter, no path guiding, no light threshold, single-scattering GGX,
  fixed seed and thread count.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["reset", "settings", "add_mesh", "add_camera", "add_lights", "add_world",
           "skin_material", "render_pixels"]

BOUNCES = 1024  # Cycles' path length cap per kind, its largest (default 12 cuts light; the
                # reference has none: a path in skin scatters hundreds of times)


def reset():
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def settings(scene, *, width: int, height: int, threads: int) -> None:
    """Render settings of a faithful comparison (module docstring)."""
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.use_adaptive_sampling = False
    cy.use_denoising = False
    cy.use_animated_seed = False
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 1.0
    cy.sample_clamp_direct = 0.0
    cy.sample_clamp_indirect = 0.0
    cy.blur_glossy = 0.0
    cy.light_sampling_threshold = 0.0
    cy.use_guiding = False
    cy.max_bounces = BOUNCES
    for kind in ("diffuse", "glossy", "transmission", "transparent_max"):
        setattr(cy, f"{kind}_bounces", BOUNCES)
    cy.volume_step_rate = 1.0
    cy.volume_bounces = BOUNCES
    cy.caustics_reflective = True
    cy.caustics_refractive = True
    scene.render.resolution_x = int(width)
    scene.render.resolution_y = int(height)
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    # the BVH built once per process, not per render: a render of the 1.1M-triangle scan
    # spent 7-12 s building it, 0.06 s with persistent data (measured at load 10)
    scene.render.use_persistent_data = True
    scene.render.threads_mode = "FIXED"
    scene.render.threads = int(threads)
    scene.view_settings.view_transform = "Raw"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.unit_settings.system = "NONE"


def _frame_matrix(origin, z_axis, hint=(0.0, 1.0, 0.0)):
    """4x4 world matrix of an object at ``origin`` whose local +z is ``z_axis``."""
    import mathutils
    z = np.asarray(z_axis, np.float64)
    z = z / np.linalg.norm(z)
    h = np.asarray(hint, np.float64)
    if abs(float(np.dot(h, z))) > 0.9:
        h = np.array([1.0, 0.0, 0.0])
    x = np.cross(h, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, origin
    return mathutils.Matrix(m.tolist())


def add_mesh(scene, vertices, faces, *, normals=None, uv=None, uv_faces=None, name="head"):
    """A smooth-shaded mesh object of dermis's arrays (mm; faces counter-clockwise outside)."""
    import bpy
    v = np.ascontiguousarray(vertices, np.float32).ravel()
    f = np.ascontiguousarray(faces, np.int32)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(v) // 3)
    me.vertices.foreach_set("co", v)
    me.loops.add(f.size)
    me.loops.foreach_set("vertex_index", f.ravel())
    me.polygons.add(len(f))
    me.polygons.foreach_set("loop_start", np.arange(0, f.size, 3, dtype=np.int32))
    me.polygons.foreach_set("use_smooth", np.ones(len(f), bool))
    if uv is not None and uv_faces is not None:
        layer = me.uv_layers.new(name="UVMap")
        corner = np.asarray(uv, np.float32)[np.asarray(uv_faces, np.int64).ravel()]
        layer.data.foreach_set("uv", np.ascontiguousarray(corner).ravel())
    me.update()
    if normals is not None:
        # Blender's smooth normals are angle-weighted, as dermis's: custom normals (20 s on
        # the 1.1M-triangle scan, measured) only where they differ (> 0.1 degree)
        have = np.empty(v.size, np.float32)
        me.vertices.foreach_get("normal", have)
        want = np.asarray(normals, np.float32)
        if np.min(np.einsum("ij,ij->i", have.reshape(-1, 3), want)) < math.cos(math.radians(0.1)):
            me.normals_split_custom_set_from_vertices(want)
    ob = bpy.data.objects.new(name, me)
    scene.collection.objects.link(ob)
    return ob


def add_camera(scene, *, position, forward, up, fov_deg: float, width: int, height: int,
               orthographic_scale: float = 0.0):
    """dermis's pinhole camera (``rendering/camera.py`` camera_vectors): looks along
    ``forward`` with ``up`` the image's up; ``orthographic_scale`` > 0: an orthographic camera
    of that width (the slab measurements)."""
    import bpy
    cam = bpy.data.cameras.new("camera")
    if orthographic_scale > 0:
        cam.type = "ORTHO"
        cam.ortho_scale = float(orthographic_scale)
    else:
        cam.type = "PERSP"
        cam.sensor_fit = "HORIZONTAL" if width <= height else "VERTICAL"
        cam.angle = math.radians(float(fov_deg))
    dist = float(np.linalg.norm(np.asarray(position, np.float64)))
    cam.clip_start = 1e-3
    cam.clip_end = 1e3 * max(dist, 1e4)
    ob = bpy.data.objects.new("camera", cam)
    fwd = np.asarray(forward, np.float64)
    upv = np.asarray(up, np.float64)
    right = np.cross(fwd, upv)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, upv, -fwd, position
    import mathutils
    ob.matrix_world = mathutils.Matrix(m.tolist())
    scene.collection.objects.link(ob)
    scene.camera = ob
    return ob


def _light(scene, kind: str, name: str, rgb, power_per_unit: float):
    """A Cycles light whose colour x energy is ``power_per_unit`` x ``rgb``."""
    import bpy
    rgb = np.asarray(rgb, np.float64)
    peak = float(rgb.max())
    light = bpy.data.lights.new(name, kind)
    light.energy = power_per_unit * peak
    light.color = tuple((rgb / peak).tolist()) if peak > 0 else (0.0, 0.0, 0.0)
    ob = bpy.data.objects.new(name, light)
    ob.visible_camera = False
    scene.collection.objects.link(ob)
    return light, ob


def add_lights(scene, lights, *, target) -> None:
    """dermis lights (dicts of ``LightConfig`` fields, environment lights excluded) as
    Cycles lights, powers from dermis's units (module docstring)."""
    target = np.asarray(target, np.float64)
    for lt in lights:
        kind = lt["type"]
        if kind == "point":
            light, ob = _light(scene, "POINT", lt["name"], lt["intensity"], 4.0 * math.pi)
            light.shadow_soft_size = 0.0
            light.use_soft_falloff = False
            ob.location = tuple(lt["position"])
        elif kind == "disc":
            light, ob = _light(scene, "AREA", lt["name"], lt["intensity"], math.pi)
            light.shape = "DISK"
            light.size = 2.0 * float(lt["radius"])
            c = np.asarray(lt["position"], np.float64)
            n = np.asarray(lt["direction"], np.float64)
            n = n / np.linalg.norm(n)
            if np.dot(n, target - c) < 0:
                n = -n
            ob.matrix_world = _frame_matrix(c, -n)    # an area light emits along local -z
        elif kind == "directional":
            light, ob = _light(scene, "SUN", lt["name"], lt["intensity"], 1.0)
            light.angle = math.radians(float(lt.get("angle_deg", 0.0)))
            d = np.asarray(lt["direction"], np.float64)
            ob.matrix_world = _frame_matrix(np.zeros(3), d)   # light travels along -d
        else:
            raise ValueError(f"light type {kind!r} is not a Cycles lamp")


def _image(name: str, rgb, *, interpolation: str):
    """A float Blender image of (H, W, 3) linear values, row 0 at the top (dermis's order;
    Blender stores rows bottom-up), used as data (no colour transform)."""
    import bpy
    a = np.asarray(rgb, np.float32)
    h, w = a.shape[:2]
    img = bpy.data.images.new(name, width=w, height=h, alpha=False, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"   # before the pixels: it reloads the buffer
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = a[::-1]
    img.pixels.foreach_set(rgba.ravel())
    img.update()
    return img, interpolation


def add_world(scene, radiance=None, *, rotation_deg: float = 0.0) -> None:
    """The world: black, or dermis's lat-long ``radiance`` map looked up as dermis does:
    u = (atan2(-x, z) - rotation) / 2 pi + 0.5, row = theta / pi (y up), nearest pixel."""
    import bpy
    world = bpy.data.worlds.new("world")
    scene.world = world
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    nt.links.new(bg.outputs[0], out.inputs["Surface"])
    if radiance is None:
        bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        bg.inputs["Strength"].default_value = 0.0
        return
    rad = np.asarray(radiance, np.float32)
    img, _ = _image("environment", rad, interpolation="Closest")
    coord = nt.nodes.new("ShaderNodeTexCoord")
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(coord.outputs["Generated"], sep.inputs[0])

    def math_node(op, a, b=None):
        n = nt.nodes.new("ShaderNodeMath")
        n.operation = op
        for i, x in enumerate((a, b)):
            if x is None:
                continue
            if isinstance(x, (int, float)):
                n.inputs[i].default_value = float(x)
            else:
                nt.links.new(x, n.inputs[i])
        return n.outputs[0]

    x, y, z = sep.outputs[0], sep.outputs[1], sep.outputs[2]
    phi = math_node("ARCTAN2", math_node("MULTIPLY", x, -1.0), z)
    u = math_node("FRACT", math_node("ADD", math_node("MULTIPLY", phi, 1.0 / (2.0 * math.pi)),
                                     0.5 - math.radians(rotation_deg) / (2.0 * math.pi)))
    length = nt.nodes.new("ShaderNodeVectorMath")
    length.operation = "LENGTH"
    nt.links.new(coord.outputs["Generated"], length.inputs[0])
    cos_t = math_node("DIVIDE", y, length.outputs["Value"])
    v = math_node("SUBTRACT", 1.0, math_node("MULTIPLY", math_node("ARCCOSINE", cos_t),
                                             1.0 / math.pi))
    comb = nt.nodes.new("ShaderNodeCombineXYZ")
    nt.links.new(u, comb.inputs[0])
    nt.links.new(v, comb.inputs[1])
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = img
    tex.interpolation = "Closest"
    tex.extension = "EXTEND"
    nt.links.new(comb.outputs[0], tex.inputs["Vector"])
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 1.0
    world.cycles.sampling_method = "MANUAL"
    world.cycles.sample_map_resolution = int(max(rad.shape[1], 1024))


def skin_material(obj, *, method: str, base_colour=None, base_texture=None, radius=(1, 1, 1),
                  ior: float = 1.4, roughness: float = 0.3, anisotropy: float = 0.0,
                  subsurface_ior: float | None = None, volume: dict | None = None):
    """Principled BSDF with subsurface weight 1 (``method``: BURLEY, RANDOM_WALK or
    RANDOM_WALK_SKIN; LAMBERT: a diffuse surface of the base colour instead; VOLUME: the
    homogeneous medium ``volume`` inside a smooth dielectric of index ``ior``), ``radius`` in mm, single-scattering GGX of alpha ``roughness``
    (Cycles' roughness input is sqrt(alpha)); base colour constant or the (H, W, 3) linear
    ``base_texture`` (row 0 at the top) through the mesh's UVs, bilinear."""
    import bpy
    mat = bpy.data.materials.new("skin")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if method == "VOLUME":    # the cross-check's material: a medium in a smooth dielectric
        _volume(nt, out, volume, ior)
        obj.data.materials.clear()
        obj.data.materials.append(mat)
        return mat
    if method == "LAMBERT":   # the unit checks' material: albedo / pi
        p = nt.nodes.new("ShaderNodeBsdfDiffuse")
        nt.links.new(p.outputs[0], out.inputs["Surface"])
        _base_colour(nt, p.inputs["Color"], base_colour, base_texture)
        obj.data.materials.clear()
        obj.data.materials.append(mat)
        return mat
    p = nt.nodes.new("ShaderNodeBsdfPrincipled")
    nt.links.new(p.outputs[0], out.inputs["Surface"])
    p.distribution = "GGX"
    p.subsurface_method = method
    p.inputs["Subsurface Weight"].default_value = 1.0
    p.inputs["Subsurface Radius"].default_value = tuple(float(r) for r in radius)
    p.inputs["Subsurface Scale"].default_value = 1.0
    p.inputs["IOR"].default_value = float(ior)
    p.inputs["Roughness"].default_value = math.sqrt(float(roughness))
    if method != "BURLEY":
        p.inputs["Subsurface Anisotropy"].default_value = float(anisotropy)
    if method == "RANDOM_WALK_SKIN":
        p.inputs["Subsurface IOR"].default_value = float(subsurface_ior or ior)
    _base_colour(nt, p.inputs["Base Color"], base_colour, base_texture)
    obj.data.materials.clear()
    obj.data.materials.append(mat)
    return mat


def _volume(nt, out, volume: dict, ior: float) -> None:
    """A smooth glass boundary of index ``ior`` around a homogeneous medium (1/mm):
    Cycles' Volume Scatter has sigma_s = colour x density, Volume Absorption sigma_a =
    (1 - colour) x density (Blender manual, "Volume Scatter", "Volume Absorption")."""
    glass = nt.nodes.new("ShaderNodeBsdfGlass")
    glass.distribution = "GGX"
    glass.inputs["Roughness"].default_value = 0.0
    glass.inputs["IOR"].default_value = float(ior)
    glass.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    nt.links.new(glass.outputs[0], out.inputs["Surface"])
    ss = np.asarray(volume["sigma_s"], np.float64)
    sa = np.asarray(volume["sigma_a"], np.float64)
    scatter = nt.nodes.new("ShaderNodeVolumeScatter")
    scatter.inputs["Color"].default_value = (*(ss / ss.max()).tolist(), 1.0)
    scatter.inputs["Density"].default_value = float(ss.max())
    scatter.inputs["Anisotropy"].default_value = float(volume.get("g", 0.0))
    absorb = nt.nodes.new("ShaderNodeVolumeAbsorption")
    absorb.inputs["Color"].default_value = (*(1.0 - sa / sa.max()).tolist(), 1.0)
    absorb.inputs["Density"].default_value = float(sa.max())
    add = nt.nodes.new("ShaderNodeAddShader")
    nt.links.new(scatter.outputs[0], add.inputs[0])
    nt.links.new(absorb.outputs[0], add.inputs[1])
    nt.links.new(add.outputs[0], out.inputs["Volume"])


def _base_colour(nt, socket, base_colour, base_texture) -> None:
    """Feed ``socket`` a constant colour or the texture through the UVs (bilinear)."""
    if base_texture is not None:
        img, _ = _image("base_colour", base_texture, interpolation="Linear")
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = img
        tex.interpolation = "Linear"
        tex.extension = "EXTEND"
        uvn = nt.nodes.new("ShaderNodeUVMap")
        uvn.uv_map = "UVMap"
        nt.links.new(uvn.outputs["UV"], tex.inputs["Vector"])
        nt.links.new(tex.outputs["Color"], socket)
    else:
        c = np.asarray(base_colour if base_colour is not None else (0.8, 0.8, 0.8), float)
        socket.default_value = (*c.tolist(), 1.0)


def render_pixels(scene, *, seed: int, spp: int, scratch: str) -> np.ndarray:
    """Render at ``spp`` samples with ``seed``; (H, W, 4) float32 premultiplied RGBA, row 0
    at the top.  The render result is written as a 32-bit EXR (scene-linear, no view
    transform) and read back: Blender exposes no render result pixels otherwise."""
    import bpy
    scene.cycles.seed = int(seed)
    scene.cycles.samples = int(spp)
    bpy.ops.render.render()
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.image_settings.color_mode = "RGBA"
    bpy.data.images["Render Result"].save_render(scratch)
    img = bpy.data.images.load(scratch)
    w, h = img.size
    a = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(a)
    bpy.data.images.remove(img)
    return a.reshape(h, w, 4)[::-1].copy()
