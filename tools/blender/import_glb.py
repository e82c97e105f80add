"""Opens a lifegom `.glb` with Blender's own glTF importer and reports what Blender made of it.

Run headless, as tests/tests/rig_export.rs does:

    blender -b --factory-startup --python-exit-code 1 -P tools/blender/import_glb.py -- \
        AVATAR.glb REPORT.json STILL.png ANIMATION KEYFRAME

It imports the file into an empty scene, plays animation ANIMATION at its keyframe KEYFRAME
(0-based, in the order of the file's keyframe times), evaluates the deformed mesh through the
armature modifier, and writes REPORT.json:

- `bones`: the armature's bone names; `vertex_groups`: the mesh's vertex group names;
  `modifiers`: the mesh's modifier types; `actions`: the imported actions' names;
- `rest` and `posed`: every mesh vertex's world position before and after posing, flattened,
  converted back from Blender's +Z-up axes to glTF's +Y-up ones, in Blender's vertex order;
- `frame`: the scene frame the keyframe landed on, and `keyframes`: how many the action has.

Then it renders STILL.png of the posed avatar with Cycles on the CPU (a small, quick still to
look at: the vertex colours, the bones' deformation).

Debian's Blender 3.4 importer calls `numpy.bool`, which numpy 1.24 removed: the alias is put
back before importing.
"""

import json
import math
import sys

import numpy

if not hasattr(numpy, "bool"):
    numpy.bool = bool  # Blender 3.4's glTF importer predates numpy 1.24

import bpy  # noqa: E402  (after the numpy alias)
from mathutils import Vector  # noqa: E402


def gltf_axes(v):
    """Blender's +Z-up world to glTF's +Y-up: (x, y, z) -> (x, z, -y)."""
    return [v.x, v.z, -v.y]


def main():
    args = sys.argv[sys.argv.index("--") + 1 :]
    glb, report_path, still_path, animation, key = args[0], args[1], args[2], args[3], int(args[4])

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=glb)

    armatures = [o for o in bpy.data.objects if o.type == "ARMATURE"]
    meshes = [o for o in bpy.data.objects if o.type == "MESH"]
    if len(armatures) != 1 or len(meshes) != 1:
        raise SystemExit(
            f"{glb}: expected one armature and one mesh, found {len(armatures)} and {len(meshes)}"
        )
    armature, mesh = armatures[0], meshes[0]

    actions = [a.name for a in bpy.data.actions]
    # The importer names an action after its animation, with a suffix when several objects
    # take part; take the one that starts with the animation's name.
    matching = [
        a for a in bpy.data.actions if a.name == animation or a.name.startswith(animation + "_")
    ]
    if not matching:
        raise SystemExit(f"{glb}: no action for animation `{animation}` among {actions}")
    action = matching[0]
    if armature.animation_data is None:
        armature.animation_data_create()
    armature.animation_data.action = action
    times = sorted({round(p.co.x, 4) for c in action.fcurves for p in c.keyframe_points})
    if key >= len(times):
        raise SystemExit(f"{glb}: `{animation}` has {len(times)} keyframes, asked for {key}")
    frame = times[key]
    scene = bpy.context.scene
    scene.frame_set(int(math.floor(frame)), subframe=frame - math.floor(frame))

    rest = [c for v in mesh.data.vertices for c in gltf_axes(mesh.matrix_world @ v.co)]
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = mesh.evaluated_get(depsgraph)
    posed_mesh = evaluated.to_mesh()
    world = evaluated.matrix_world
    posed = [c for v in posed_mesh.vertices for c in gltf_axes(world @ v.co)]
    evaluated.to_mesh_clear()

    report = {
        "bones": [b.name for b in armature.data.bones],
        "vertex_groups": [g.name for g in mesh.vertex_groups],
        "modifiers": [m.type for m in mesh.modifiers],
        "actions": actions,
        "frame": frame,
        "keyframes": len(times),
        "rest": rest,
        "posed": posed,
    }
    with open(report_path, "w") as f:
        json.dump(report, f)

    # A still of the posed avatar, from the front (glTF +Z is Blender's -Y).
    points = [Vector(posed[i : i + 3]) for i in range(0, len(posed), 3)]
    lo = Vector((min(p.x for p in points), min(p.y for p in points), min(p.z for p in points)))
    hi = Vector((max(p.x for p in points), max(p.y for p in points), max(p.z for p in points)))
    centre_gltf = (lo + hi) / 2
    centre = Vector((centre_gltf.x, -centre_gltf.z, centre_gltf.y))
    height = hi.y - lo.y
    camera_data = bpy.data.cameras.new("camera")
    camera_data.lens = 50
    camera = bpy.data.objects.new("camera", camera_data)
    scene.collection.objects.link(camera)
    distance = 2.2 * height
    camera.location = centre + Vector((0.0, -distance, 0.0))
    camera.rotation_euler = (math.pi / 2, 0.0, 0.0)
    scene.camera = camera
    sun_data = bpy.data.lights.new("sun", "SUN")
    sun_data.energy = 3.0
    sun = bpy.data.objects.new("sun", sun_data)
    sun.rotation_euler = (math.radians(50), 0.0, math.radians(-30))
    scene.collection.objects.link(sun)
    world_data = bpy.data.worlds.new("world")
    world_data.color = (0.8, 0.8, 0.8)
    scene.world = world_data
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False  # Debian builds Blender without OpenImageDenoise
    scene.render.resolution_x = 256
    scene.render.resolution_y = 384
    scene.render.resolution_percentage = 100
    scene.render.filepath = still_path
    scene.render.image_settings.file_format = "PNG"
    bpy.ops.render.render(write_still=True)


main()
