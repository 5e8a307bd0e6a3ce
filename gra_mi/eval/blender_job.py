"""Render an exported avatar in Blender (Cycles), as a user who imports it would: run by a Python that has ``bpy``
(``python -I blender_job.py JOB.json``) or by Blender itself (``blender -b --python blender_job.py -- JOB.json``).

It imports only Blender and the standard library (it runs in Blender's own Python, not gra-mi's). The job (JSON):
``asset`` (.usd* or .glb), ``frame`` and ``fps`` (the sequence frame to show), ``envmap`` (lat-long EXR in gra-mi's
convention), ``camera`` (OpenCV ``camera_to_world`` in gra-mi's world, ``fx fy cx cy width height``), ``spp``,
``lambert`` (swap the imported Principled BSDF for a Diffuse BSDF on the same base colour), ``out`` (RGBA EXR) and
``report`` (JSON: Blender's version, the frame shown, the imported mesh's vertices at that frame in gra-mi's world).
A job with ``reexport`` (a .glb or .usd* path) instead writes the imported asset back out with Blender's exporters;
one with ``inventory`` (a JSON path) writes the cameras, lights and meshes Blender imported, in gra-mi's world (a USD's
with ``light_intensity_scale``, the importer's option of that name), at the exported ``frame`` where the job names one.

Conventions handled here, each checked by tests/test_export.py against Mitsuba:
- Blender is Z up; both importers turn a Y-up file by (x, y, z) → (x, −z, y);
- Blender's lat-long image centre looks along +X and u = 0.25 along +Y; gra-mi's centre along +Z (Blender −Y) and
  u = 0.25 along +X: the World's lookup vector is turned +90° about Z;
- a Blender camera looks along −Z with +Y up (OpenGL), an OpenCV camera along +Z with +Y down.
"""

import json
import math
import sys

import bpy
import mathutils

GRA_MI_TO_BLENDER = mathutils.Matrix(((1, 0, 0, 0), (0, 0, -1, 0), (0, 1, 0, 0), (0, 0, 0, 1)))
OPENCV_TO_OPENGL = mathutils.Matrix(((1, 0, 0, 0), (0, -1, 0, 0), (0, 0, -1, 0), (0, 0, 0, 1)))


def import_asset(path: str, rig: bool = False, light_scale: float = 1.0) -> None:
    """The asset alone (a render sets its own camera and world), or with the cameras and lights it carries (``rig``;
    ``light_scale``: the USD importer's ``light_intensity_scale``)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if path.lower().endswith(".glb"):
        bpy.ops.import_scene.gltf(filepath=path)
    else:
        bpy.ops.wm.usd_import(filepath=path, import_cameras=rig, import_lights=rig, light_intensity_scale=light_scale)


def show_frame(scene, frame: int, fps: float, glb: bool) -> int:
    """The scene frame that shows sequence frame ``frame``: USD time codes are frames; the glTF importer keys its
    animation at time × the scene's frame rate."""
    shown = int(round(frame / fps * scene.render.fps / scene.render.fps_base)) if glb else frame
    scene.frame_set(shown)
    return shown


def mesh_vertices(scene) -> list:
    """The (one) imported mesh's evaluated vertices in gra-mi's world."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    to_gra_mi = GRA_MI_TO_BLENDER.inverted()
    for obj in scene.objects:
        if obj.type == "MESH":
            evaluated = obj.evaluated_get(depsgraph)
            matrix = to_gra_mi @ evaluated.matrix_world
            return [list(matrix @ v.co) for v in evaluated.to_mesh().vertices]
    raise RuntimeError("the asset holds no mesh")


def use_lambert(scene) -> None:
    for obj in scene.objects:
        for slot in getattr(obj, "material_slots", []):
            tree = slot.material.node_tree
            principled = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
            output = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
            diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
            base = principled.inputs["Base Color"]
            if base.is_linked:
                tree.links.new(base.links[0].from_socket, diffuse.inputs["Color"])
            else:
                diffuse.inputs["Color"].default_value = base.default_value
            tree.links.new(diffuse.outputs["BSDF"], output.inputs["Surface"])


def use_distribution(scene, distribution: str) -> None:
    """Set every imported Principled BSDF's microfacet distribution ('GGX': single scattering, as gra-mi's BRDF;
    Blender's default 'MULTI_GGX' adds the light of multiple scattering between microfacets)."""
    for obj in scene.objects:
        for slot in getattr(obj, "material_slots", []):
            for node in slot.material.node_tree.nodes:
                if node.type == "BSDF_PRINCIPLED":
                    node.distribution = distribution


def set_world(scene, envmap: str) -> None:
    world = bpy.data.worlds.new("gra-mi envmap")
    scene.world = world
    world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    coords, mapping, texture = nodes.new("ShaderNodeTexCoord"), nodes.new("ShaderNodeMapping"), nodes.new("ShaderNodeTexEnvironment")
    texture.image = bpy.data.images.load(envmap)
    texture.image.colorspace_settings.name = "Linear Rec.709"
    texture.interpolation = "Linear"
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(90.0))
    links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
    links.new(texture.outputs["Color"], nodes["Background"].inputs["Color"])
    nodes["Background"].inputs["Strength"].default_value = 1.0


def set_camera(scene, spec: dict) -> None:
    data = bpy.data.cameras.new("capture camera")
    camera = bpy.data.objects.new("capture camera", data)
    scene.collection.objects.link(camera)
    scene.camera = camera
    c2w = mathutils.Matrix(spec["camera_to_world"])
    camera.matrix_world = GRA_MI_TO_BLENDER @ c2w @ OPENCV_TO_OPENGL
    width, height = spec["width"], spec["height"]
    if width >= height:  # Blender fits the sensor to the image's long side; shifts are fractions of that side
        data.sensor_fit, data.sensor_width, data.lens = "HORIZONTAL", 36.0, spec["fx"] * 36.0 / width
    else:
        data.sensor_fit, data.sensor_height, data.lens = "VERTICAL", 36.0, spec["fy"] * 36.0 / height
    data.shift_x = (width / 2.0 - spec["cx"]) / max(width, height)
    data.shift_y = (spec["cy"] - height / 2.0) / max(width, height)
    data.clip_start, data.clip_end = 0.01, 100.0
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = 1.0, spec["fx"] / spec["fy"]


def set_cycles(scene, spp: int, seed: int) -> None:
    scene.render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device, cycles.samples, cycles.seed = "CPU", spp, seed
    cycles.use_adaptive_sampling, cycles.use_denoising = False, False
    cycles.max_bounces = 0  # direct light only: gra-mi's one bounce, Mitsuba's path with max_depth 2
    cycles.sample_clamp_direct = cycles.sample_clamp_indirect = 0.0
    cycles.pixel_filter_type, cycles.filter_width = "BOX", 1.0
    scene.render.film_transparent = True
    scene.view_settings.view_transform, scene.view_settings.look = "Standard", "None"
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    settings = scene.render.image_settings
    settings.file_format, settings.color_mode, settings.color_depth = "OPEN_EXR", "RGBA", "32"


def reexport(path: str) -> None:
    """Write what was imported as Blender writes it (an avatar edited in Blender and handed back to gra-mi)."""
    if path.lower().endswith(".glb"):
        bpy.ops.export_scene.gltf(filepath=path, export_format="GLB")
    else:
        bpy.ops.wm.usd_export(filepath=path, export_animation=True)


def inventory(path: str) -> None:
    """The imported cameras (camera-to-world with OpenCV axes, vertical field of view) and lights (type, position,
    power in W, colour), in gra-mi's world."""
    to_gra_mi = GRA_MI_TO_BLENDER.inverted()
    cameras, lights = [], []
    for obj in bpy.context.scene.objects:
        world = to_gra_mi @ obj.matrix_world
        if obj.type == "CAMERA":
            c2w = world @ OPENCV_TO_OPENGL.inverted()
            cameras.append({"name": obj.name, "camera_to_world": [list(row) for row in c2w], "angle_y": obj.data.angle_y})
        elif obj.type == "LIGHT":
            lights.append(light_entry(obj, world))
    meshes = [mesh_entry(obj, to_gra_mi) for obj in bpy.context.scene.objects if obj.type == "MESH"]
    with open(path, "w") as fh:
        json.dump({"blender": bpy.app.version_string, "cameras": cameras, "lights": lights, "meshes": meshes}, fh)


def light_entry(obj, world) -> dict:
    """A light's type, position, power (W) and colour; a spot's cone (Blender's full angle and blend) and the
    direction it shines along (its −Z), in gra-mi's world (``world``: its matrix there)."""
    data = obj.data
    entry = {"name": obj.name, "type": data.type, "position": list(world.translation), "energy": data.energy, "color": list(data.color)}
    if data.type == "SPOT":
        shine = world.to_3x3() @ mathutils.Vector((0.0, 0.0, -1.0))
        entry |= {"spot_size": data.spot_size, "spot_blend": data.spot_blend, "direction": list(shine.normalized())}
    return entry


def mesh_entry(obj, to_gra_mi) -> dict:
    """A mesh's name, its bounds in gra-mi's world, and its material's Principled BSDF inputs that are not textured."""
    world = to_gra_mi @ obj.matrix_world
    points = [world @ v.co for v in obj.data.vertices]
    entry = {"name": obj.name, "min": [min(p[i] for p in points) for i in range(3)], "max": [max(p[i] for p in points) for i in range(3)]}
    material = obj.active_material
    nodes = material.node_tree.nodes if material is not None and material.node_tree is not None else []
    for node in nodes:
        if node.type == "BSDF_PRINCIPLED":
            for name in ("Base Color", "Roughness", "Metallic", "IOR"):
                socket = node.inputs[name]
                if not socket.is_linked:
                    value = socket.default_value
                    entry[name] = list(value)[:3] if name == "Base Color" else float(value)
    return entry


def main(job_path: str) -> None:
    job = json.load(open(job_path))
    import_asset(job["asset"], rig="inventory" in job, light_scale=job.get("light_intensity_scale", 1.0))
    if "reexport" in job:
        reexport(job["reexport"])
        return
    if "inventory" in job:
        if "frame" in job:  # (lights that move: where they are at that sequence frame)
            show_frame(bpy.context.scene, job["frame"], job["fps"], job["asset"].lower().endswith(".glb"))
        inventory(job["inventory"])
        return
    scene = bpy.context.scene
    glb = job["asset"].lower().endswith(".glb")
    shown = show_frame(scene, job["frame"], job["fps"], glb)
    if job.get("lambert"):
        use_lambert(scene)
    elif job.get("distribution"):
        use_distribution(scene, job["distribution"])
    set_world(scene, job["envmap"])
    set_camera(scene, job["camera"])
    set_cycles(scene, job["spp"], job.get("seed", 0))
    scene.render.filepath = job["out"]
    bpy.ops.render.render(write_still=True)
    report = {"blender": bpy.app.version_string, "scene_frame": shown, "vertices": mesh_vertices(scene)}
    with open(job["report"], "w") as fh:
        json.dump(report, fh)


if __name__ == "__main__":
    main(sys.argv[-1])
