"""What the headless Blender session scripts share (each runs as its own process with this folder on sys.path):
blocking torch as a Blender without PyTorch would, steps whose result or traceback is recorded for the test to
assert on, an empty scene with its camera above the card, and selecting objects. bpy is imported only inside the
functions, so a script can block torch before anything imports bpy."""
import sys
import traceback


class TorchBlocker:
    """Makes `import torch` fail as it would in a Blender without PyTorch."""

    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"No module named '{name}' (blocked by the test)")
        return None


def block_torch() -> TorchBlocker:
    """Block torch from now on; `sys.meta_path.remove(blocker)` lifts it."""
    blocker = TorchBlocker()
    sys.meta_path.insert(0, blocker)
    return blocker


def recorder(results: dict, trace_chars: int = 2000):
    """A `@step(name)` decorator that runs the function at once and stores its result, or the error and the end
    of its traceback, in results[name]."""
    def step(name):
        def deco(fn):
            try:
                results[name] = fn()
            except Exception as exc:  # recorded, the test asserts on it
                results[name] = {"error": f"{type(exc).__name__}: {exc}",
                                 "trace": traceback.format_exc()[-trace_chars:]}
            return fn
        return deco
    return step


def camera_only_scene():
    """Every object but the cameras removed, the scene camera 3 units above the origin looking down −Z (at the
    card in the plane z = 0). Returns (scene, camera)."""
    import bpy

    scene = bpy.context.scene
    for o in list(bpy.data.objects):
        if o.type != 'CAMERA':
            bpy.data.objects.remove(o)
    cam = scene.camera
    cam.location = (0.0, 0.0, 3.0)
    cam.rotation_euler = (0.0, 0.0, 0.0)
    return scene, cam


def drop_ids_modifier(obj, distance: float):
    """Add a Geometry Nodes modifier that removes the pointgt_id attribute and merges points closer than
    `distance`: the point count changes and the ids are gone, as a careless node setup would leave them."""
    import bpy

    ng = bpy.data.node_groups.new("drop ids", 'GeometryNodeTree')
    ng.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    ng.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    gin, gout = ng.nodes.new('NodeGroupInput'), ng.nodes.new('NodeGroupOutput')
    remove = ng.nodes.new('GeometryNodeRemoveAttribute')
    remove.inputs["Name"].default_value = "pointgt_id"
    merge = ng.nodes.new('GeometryNodeMergeByDistance')
    merge.inputs["Distance"].default_value = distance
    ng.links.new(gin.outputs[0], remove.inputs[0])
    ng.links.new(remove.outputs[0], merge.inputs[0])
    ng.links.new(merge.outputs[0], gout.inputs[0])
    mod = obj.modifiers.new("drop", 'NODES')
    mod.node_group = ng
    return mod


def make_active(obj, *others):
    """Select obj and others, obj active."""
    import bpy

    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in (obj, *others):
        o.select_set(True)
    bpy.context.view_layer.objects.active = obj
