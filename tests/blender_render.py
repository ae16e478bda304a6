"""Render small test scenes with Blender's Cycles on the CPU (run by a Python that has `bpy`).

    python blender_render.py JOBS.json

JOBS (written by tests/tool_scenes.py) is {"jobs": [SPEC, ...]}: one process renders them all
(importing bpy costs ~5 s, a 64 x 64 render ~2 s). Each SPEC says what to build, from Blender's
factory settings; nothing here knows about wavelight:
  world:   {"mode": "nodes", "image": PATH}    a World built here by hand: Environment Texture
                                               (equirectangular, no mapping) -> Background, strength 1
           {"mode": "script", "script": PATH}  the world made by running that script (the export's
                                               setup_world.py), as `blender --python` would
           {"mode": "text", "script": PATH}    the same script opened in a Text Editor block and run
                                               with Run Script (bpy.ops.text.run_script)
  render:  false to only describe the world (output_world: a JSON of its nodes, links and image)
  camera:  {"matrix": 4x4 camera -> world (Blender's camera looks along its local -Z, +Y up),
            "type": "PERSP" (with "lens_mm", "sensor_mm", horizontal fit) | "ORTHO" (with "ortho_scale")}
  width, height, samples, seed, threads, output (a multilayer EXR: Combined, Normal and Position
           passes, each the mean over the pixel's samples)
  objects: [{"kind": "sphere", "center", "radius"} | {"kind": "plane", "size", "z"},
            each with "material": {"type": "diffuse", "color"} | {"type": "glossy", "color",
            "roughness", "distribution"} | {"type": "script", "script": PATH} (the export's
            setup_material.py run as `blender --python` runs it, the object active), "visible_camera" (default true) and "camera_only"
            (default false: seen by camera rays alone, so that two spheres in one image neither
            shadow nor reflect each other)]

Everything that could change the numbers is fixed: no denoising, no adaptive sampling, no clamping,
a box pixel filter (one pixel wide whatever filter_width says -- measured: the Normal pass is the
pixel-area mean of the sphere's normals -- so each pixel integrates its area, as the references
do), exposure 0, view transform Standard (the EXR is linear either way), the image read as linear
Rec.709.
"""

from __future__ import annotations

import json
import runpy
import sys

import bpy


def _material(spec: dict):
    mat = bpy.data.materials.new(spec["type"])
    nt = mat.node_tree if mat.node_tree is not None else None
    if nt is None:  # Blender < 5 needs use_nodes to get a tree
        mat.use_nodes = True
        nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if spec["type"] == "diffuse":
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Roughness"].default_value = 0.0  # Lambert (Oren-Nayar off)
    elif spec["type"] == "glossy":
        bsdf = nt.nodes.new("ShaderNodeBsdfGlossy")
        bsdf.distribution = spec.get("distribution", "GGX")
        bsdf.inputs["Roughness"].default_value = float(spec["roughness"])  # alpha = roughness^2
    else:
        raise ValueError(f"unknown material type {spec['type']!r}")
    bsdf.inputs["Color"].default_value = (*spec.get("color", (1.0, 1.0, 1.0)), 1.0)
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return mat


def _sphere(spec: dict):
    """An exact sphere: a one-point point cloud (Cycles renders points as true spheres)."""
    me = bpy.data.meshes.new("point")
    me.from_pydata([(0.0, 0.0, 0.0)], [], [])
    ob = bpy.data.objects.new("sphere", me)
    bpy.context.scene.collection.objects.link(ob)
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    bpy.context.view_layer.objects.active = ob
    ob.select_set(True)
    bpy.ops.object.convert(target="POINTCLOUD")
    ob = bpy.context.view_layer.objects.active
    pc = ob.data
    if "radius" not in pc.attributes:
        pc.attributes.new("radius", "FLOAT", "POINT")
    pc.attributes["radius"].data[0].value = float(spec["radius"])
    ob.location = spec["center"]
    return ob


def _plane(spec: dict):
    h = float(spec["size"]) / 2
    z = float(spec.get("z", 0.0))
    me = bpy.data.meshes.new("plane")
    me.from_pydata([(-h, -h, z), (h, -h, z), (h, h, z), (-h, h, z)], [], [(0, 1, 2, 3)])
    ob = bpy.data.objects.new("plane", me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def hand_built_world(image_path: str, interpolation: str = "Linear"):
    """The World as a user would build it by hand: Environment Texture -> Background -> output."""
    world = bpy.data.worlds.new("hand-built")
    if world.node_tree is None:
        world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(image_path)
    env.image.colorspace_settings.name = "Linear Rec.709"
    env.projection = "EQUIRECTANGULAR"
    env.interpolation = interpolation
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = 1.0
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    bpy.context.scene.world = world


def build(spec: dict):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    w = spec["world"]
    if w["mode"] == "nodes":
        hand_built_world(w["image"], w.get("interpolation", "Linear"))
    elif w["mode"] == "script":
        runpy.run_path(w["script"], run_name="__main__")
    elif w["mode"] == "text":
        text = bpy.data.texts.load(w["script"])
        with bpy.context.temp_override(edit_text=text):
            result = bpy.ops.text.run_script()
        if result != {"FINISHED"}:
            raise RuntimeError(f"Run Script of {w['script']} returned {result}")
    else:
        raise ValueError(f"unknown world mode {w['mode']!r}")

    cam = spec["camera"]
    data = bpy.data.cameras.new("camera")
    data.type = cam["type"]
    if cam["type"] == "PERSP":
        data.sensor_fit = "HORIZONTAL"
        data.sensor_width = float(cam["sensor_mm"])
        data.lens = float(cam["lens_mm"])
    else:
        data.ortho_scale = float(cam["ortho_scale"])
    data.shift_x = data.shift_y = 0.0
    data.clip_start, data.clip_end = 0.01, 1000.0
    ob = bpy.data.objects.new("camera", data)
    scene.collection.objects.link(ob)
    from mathutils import Matrix

    ob.matrix_world = Matrix(cam["matrix"])
    scene.camera = ob

    for o in spec["objects"]:
        obj = _sphere(o) if o["kind"] == "sphere" else _plane(o)
        if o["material"]["type"] == "script":  # the export's setup_material.py, run on the active object
            bpy.context.view_layer.objects.active = obj
            runpy.run_path(o["material"]["script"], run_name="__main__")
            if not obj.data.materials or obj.data.materials[0] is None:
                raise RuntimeError(f"{o['material']['script']} gave the object no material")
        else:
            obj.data.materials.append(_material(o["material"]))
        obj.visible_camera = bool(o.get("visible_camera", True))
        if o.get("camera_only", False):
            obj.visible_diffuse = obj.visible_glossy = obj.visible_transmission = False
            obj.visible_volume_scatter = obj.visible_shadow = False

    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = int(spec["width"]), int(spec["height"]), 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.film_transparent = False
    r.use_border = False
    r.threads_mode = "FIXED"
    r.threads = int(spec.get("threads", 2))
    c = scene.cycles
    c.device = "CPU"
    c.samples = int(spec["samples"])
    c.seed = int(spec["seed"])
    c.use_animated_seed = False
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0  # the box is one pixel wide anyway
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.max_bounces = 1  # a lone convex object: nothing to bounce off; 1 keeps BSDF-sampled world hits
    c.diffuse_bounces = c.glossy_bounces = 1
    c.caustics_reflective = c.caustics_refractive = True
    c.use_guiding = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.view_layers[0].use_pass_normal = True
    scene.view_layers[0].use_pass_position = True
    img = r.image_settings
    if hasattr(img, "media_type"):  # Blender 5: multilayer is a media type of OpenEXR
        img.media_type = "MULTI_LAYER_IMAGE"
    img.file_format = "OPEN_EXR_MULTILAYER"
    img.color_depth = "32"
    img.exr_codec = "ZIP"
    r.filepath = spec.get("output", "")
    r.use_file_extension = False
    return scene


def describe_world(world) -> dict:
    """The world's node graph: node types with their settings, links, the image's file and colour
    space (what a setup script must get right)."""
    nodes = {}
    for n in world.node_tree.nodes:
        d = {"type": n.bl_idname}
        if n.bl_idname == "ShaderNodeTexEnvironment":
            d.update(image=bpy.path.abspath(n.image.filepath) if n.image else None,
                     colorspace=n.image.colorspace_settings.name if n.image else None,
                     projection=n.projection, interpolation=n.interpolation)
        if n.bl_idname == "ShaderNodeBackground":
            d["strength"] = n.inputs["Strength"].default_value
        if n.bl_idname == "ShaderNodeMapping":
            d.update(vector_type=n.vector_type, **{k: list(n.inputs[k].default_value)
                                                  for k in ("Location", "Rotation", "Scale")})
        nodes[n.name] = d
    links = sorted([l.from_node.bl_idname, l.from_socket.identifier, l.to_node.bl_idname, l.to_socket.identifier]
                   for l in world.node_tree.links)
    return {"name": world.name, "nodes": sorted(nodes.values(), key=lambda d: d["type"]), "links": links}


def main(argv: list[str]) -> None:
    with open(argv[-1]) as f:
        jobs = json.load(f)["jobs"]
    for spec in jobs:
        scene = build(spec)
        if spec.get("output_world"):
            with open(spec["output_world"], "w") as f:
                json.dump(describe_world(scene.world), f, indent=1)
        if spec.get("render", True):
            bpy.ops.render.render(write_still=True)
            print(f"blender_render: wrote {spec['output']}")


if __name__ == "__main__":
    main(sys.argv)
