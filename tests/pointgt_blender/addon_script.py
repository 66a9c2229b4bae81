"""Run inside a fresh Blender (bpy) subprocess by test_addon_blender.py; prints one JSON line "RESULTS: {...}".

argv after "--": zip model.pgt corrupt.pgt workdir wheel_dir
Each step records what it observed (or the error) so that one failure does not hide the others.
torch is blocked (a sys.meta_path finder) until the "torch_unblocked" step, to prove the add-on works without it.
"""
import importlib
import json
import os
import sys

import numpy as np


from script_common import block_torch, drop_ids_modifier, make_active, recorder

BLOCKER = block_torch()

import bpy  # noqa: E402

zip_path, model, corrupt, work, wheels = sys.argv[sys.argv.index("--") + 1:]
R = {}
PKG = "bl_ext.user_default.pointgt"


step = recorder(R, trace_chars=1500)


def evaluated(obj):
    ev = importlib.import_module(PKG + ".scene.evaluated")
    return ev.evaluated_points(obj, bpy.context.evaluated_depsgraph_get(), 'WORLD')



def op_error(fn, **kw):
    """Run an operator that should fail; return its error text ('' if it did not fail)."""
    try:
        res = fn(**kw)
    except RuntimeError as exc:
        return str(exc)
    return "" if 'CANCELLED' not in res else "CANCELLED without message"


@step("install")
def _():
    res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    return {"result": sorted(res), "enabled": PKG in bpy.context.preferences.addons,
            "torch_loaded": "torch" in sys.modules,
            "import_op": hasattr(bpy.types, "POINTGT_OT_import_model"),
            "undo": {name: 'UNDO' in getattr(bpy.ops.pointgt, name).bl_options  # as registered with Blender
                     for name in ("reset_canonical", "bind_armature", "add_lattice", "pack_model", "transfer_paint",
                                  "export_deformed")}}


@step("torch_missing")
def _():
    deps = importlib.import_module(PKG + ".bridge.deps")
    st = deps.torch_status(refresh=True)
    return {"available": st.available, "message": st.message}


@step("import")
def _():
    before = len(bpy.data.objects)
    res = bpy.ops.pointgt.import_model(filepath=model, neighbors=12, device='CPU')
    obj = bpy.context.active_object
    mesh = obj.data
    ids = np.empty(len(mesh.vertices), np.int32)
    mesh.attributes["pointgt_id"].data.foreach_get("value", ids)
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    img = obj.pointgt.atlas
    atlas = importlib.import_module(PKG + ".scene.atlas_image").read_atlas_image(img)
    attr = mesh.attributes["pointgt_id"]
    return {"result": sorted(res), "new_objects": len(bpy.data.objects) - before, "name": obj.name,
            "verts": len(mesh.vertices), "edges": len(mesh.edges), "faces": len(mesh.polygons),
            "ids": ids.tolist(), "co": co.tolist(), "attr": [attr.domain, attr.data_type],
            "image_size": list(img.size), "packed": img.packed_file is not None, "image_float": img.is_float,
            "atlas": atlas.tolist(), "k": obj.pointgt.neighbors, "model_path": obj.pointgt.model_path,
            "point_count": obj.pointgt.point_count,
            "torch_poll_error": op_error(bpy.ops.pointgt.check_device)}  # active model, torch still blocked


@step("import_corrupt")
def _():
    counts = (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.images))
    err = op_error(bpy.ops.pointgt.import_model, filepath=corrupt)
    missing = op_error(bpy.ops.pointgt.import_model, filepath=os.path.join(work, "nope.pgt"))
    after = (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.images))
    try:  # a failure half-way (here: a bad setting, after mesh, image and object exist) leaves nothing behind
        importlib.import_module(PKG + ".operators.model_import").import_model(bpy.context, model, correspondence="BAD")
        late = ""
    except Exception as exc:
        late = f"{type(exc).__name__}: {exc}"
    after_late = (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.images))
    return {"error": err, "missing": missing, "unchanged": counts == after, "late": late,
            "unchanged_late": counts == after_late}


@step("lattice")
def _():
    obj = bpy.data.objects[R["import"]["name"]]
    make_active(obj)
    rest, _ = evaluated(obj)
    bpy.ops.pointgt.add_lattice(resolution=(3, 3, 3))
    lat = obj.modifiers["PointGT Lattice"].object
    same, _ = evaluated(obj)
    pts = lat.data.points
    top = max(range(len(pts)), key=lambda i: pts[i].co[2])
    pts[top].co_deform.z += 1.0  # pull one top corner up
    bpy.context.view_layer.update()
    moved, ids = evaluated(obj)
    return {"identity_err": float(np.abs(same - rest).max()), "max_move": float(np.abs(moved - rest).max()),
            "finite": bool(np.isfinite(moved).all()), "ids_ok": ids.tolist() == list(range(len(rest))),
            "lattice_type": lat.type}


@step("reset")
def _():
    obj = bpy.data.objects[R["import"]["name"]]
    make_active(obj)
    co = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    obj.data.vertices.foreach_set("co", co + 0.25)  # an edit-mode style change of the mesh itself
    obj.data.update()
    bpy.ops.pointgt.reset_canonical(action='DISABLE', restore_positions=True)
    pos, _ = evaluated(obj)
    canon = np.asarray(R["import"]["co"], np.float32).reshape(-1, 3)
    disabled = [m.show_viewport for m in obj.modifiers]
    bpy.ops.pointgt.reset_canonical(action='REMOVE')
    return {"err": float(np.abs(pos - canon).max()), "disabled": disabled, "left": len(obj.modifiers)}


@step("armature_envelope")
def _():
    obj = bpy.data.objects[R["import"]["name"]]
    bpy.ops.object.armature_add(location=(0.0, 0.0, -1.0))  # one bone from z=-1 to z=0
    arm = bpy.context.active_object
    bone = arm.data.bones[0]
    bone.head_radius = bone.tail_radius = 0.3  # small: some points end up outside the envelope
    bone.envelope_distance = 0.2
    make_active(obj, arm)
    rest, _ = evaluated(obj)
    bpy.ops.pointgt.bind_armature(mode='ENVELOPE')
    pb = arm.pose.bones[0]
    pb.rotation_mode = 'XYZ'
    pb.rotation_euler = (0.6, 0.0, 0.0)
    bpy.context.view_layer.update()
    posed, _ = evaluated(obj)
    R["_arm"] = arm.name
    cover = importlib.import_module(PKG + ".operators.rig").envelope_coverage(obj, arm)
    move = np.abs(posed - rest).max(axis=1)
    return {"max_move": float(np.abs(posed - rest).max()), "finite": bool(np.isfinite(posed).all()),
            "uncovered": int((cover <= 0).sum()), "uncovered_move": float(move[cover <= 0].max(initial=0.0)),
            "covered_still": int((move[cover > 1e-3] < 1e-6).sum()),
            "modifier": [m.type for m in obj.modifiers]}


@step("export")
def _():
    obj = bpy.data.objects[R["import"]["name"]]
    make_active(obj)
    base = os.path.join(work, "posed.npy")
    bpy.ops.pointgt.export_deformed(filepath=base)
    pos = np.load(os.path.join(work, "posed_positions.npy"), allow_pickle=False)
    ids = np.load(os.path.join(work, "posed_ids.npy"), allow_pickle=False)
    want, want_ids = evaluated(obj)
    bpy.ops.pointgt.export_deformed(filepath=base)  # again: the first files become .bak
    return {"shape": list(pos.shape), "dtype": str(pos.dtype), "ids_dtype": str(ids.dtype),
            "equal": bool(np.array_equal(pos, want) and np.array_equal(ids, want_ids)),
            "bak": os.path.exists(os.path.join(work, "posed_positions.npy.bak"))
            and os.path.exists(os.path.join(work, "posed_ids.npy.bak"))}


@step("armature_proxy")
def _():
    bpy.ops.pointgt.import_model(filepath=model)
    obj = bpy.context.active_object
    arm = bpy.data.objects[R["_arm"]]
    bpy.ops.mesh.primitive_cube_add(size=3.0)
    proxy = bpy.context.active_object
    group = proxy.vertex_groups.new(name=arm.data.bones[0].name)
    group.add(list(range(len(proxy.data.vertices))), 1.0, 'REPLACE')
    make_active(obj, arm, proxy)
    err_no_groups = op_error(bpy.ops.pointgt.bind_armature, mode='PROXY', proxy=R["import"]["name"])
    rest, _ = evaluated(obj)
    bpy.ops.pointgt.bind_armature(mode='PROXY', armature=arm.name, proxy=proxy.name)
    posed, _ = evaluated(obj)
    weights = [v.groups[0].weight if len(v.groups) else 0.0 for v in obj.data.vertices]
    return {"groups": [g.name for g in obj.vertex_groups], "min_weight": float(min(weights)),
            "max_move": float(np.abs(posed - rest).max()), "modifiers": [m.type for m in obj.modifiers],
            "err_no_groups": err_no_groups}


@step("nan_positions")
def _():
    bpy.ops.pointgt.import_model(filepath=model)
    obj = bpy.context.active_object
    co = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    co[3:6] = np.nan  # point id 1
    obj.data.vertices.foreach_set("co", co)
    obj.data.update()
    return {"error": op_error(bpy.ops.pointgt.export_deformed, filepath=os.path.join(work, "nan.npy")),
            "written": os.path.exists(os.path.join(work, "nan_positions.npy"))}


@step("count_changed")
def _():
    bpy.ops.pointgt.import_model(filepath=model)
    obj = bpy.context.active_object
    obj.data.attributes.remove(obj.data.attributes["pointgt_id"])
    obj.data.vertices.add(3)
    obj.data.update()
    ev = importlib.import_module(PKG + ".scene.evaluated")
    try:
        ev.evaluated_points(obj, bpy.context.evaluated_depsgraph_get())
        direct = ""
    except Exception as exc:
        direct = f"{type(exc).__name__}: {exc}"
    # realistic: a Geometry Nodes modifier drops the id attribute and merges points
    bpy.ops.pointgt.import_model(filepath=model)
    obj = bpy.context.active_object
    drop_ids_modifier(obj, 0.3)
    make_active(obj)
    n_eval = len(obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data.vertices)
    err = op_error(bpy.ops.pointgt.export_deformed, filepath=os.path.join(work, "merged.npy"))
    return {"direct": direct, "n_eval": n_eval, "op_error": err}


@step("reload_blend")
def _():
    path = os.path.join(work, "scene.blend")
    name = R["import"]["name"]
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    obj = bpy.data.objects[name]
    atlas = importlib.import_module(PKG + ".scene.atlas_image").read_atlas_image(obj.pointgt.atlas)
    return {"atlas": atlas.tolist(), "k": obj.pointgt.neighbors, "model_path": obj.pointgt.model_path,
            "resolved": os.path.samefile(bpy.path.abspath(obj.pointgt.model_path), model)}


class Layout:
    """Stands in for a UI layout (headless Blender draws no panels); checks every prop and operator named."""
    calls = []

    def __getattr__(self, name):
        def call(*args, **kw):
            if name == "prop":
                data, prop = args[0], args[1]
                assert prop in data.bl_rna.properties, f"no property {prop!r} on {data}"
            if name == "operator":
                mod, op = args[0].split(".")
                getattr(getattr(bpy.ops, mod), op).get_rna_type()  # KeyError when it does not exist
            Layout.calls.append((name, args[1] if name == "prop" else (args[0] if args else kw.get("text", ""))))
            return Layout()
        return call


@step("draw_ui")
def _():
    prefs = importlib.import_module(PKG + ".ui.preferences")
    panel = importlib.import_module(PKG + ".ui.view3d_panel").POINTGT_PT_main
    fake = type("Fake", (), {"layout": Layout(), "draw_body": panel.draw_body})()  # the panel's own methods
    bpy.context.view_layer.objects.active = None
    panel.draw(fake, bpy.context)
    no_model = list(Layout.calls)
    Layout.calls.clear()
    make_active(bpy.data.objects[R["import"]["name"]])
    panel.draw(fake, bpy.context)
    with_model = list(Layout.calls)
    Layout.calls.clear()
    addon_prefs = bpy.context.preferences.addons[PKG].preferences
    fake_prefs = type("P", (), {"layout": Layout(), "site_packages": "/nonexistent", "bl_rna": addon_prefs.bl_rna})
    prefs.PointGTPreferences.draw(fake_prefs(), bpy.context)
    labels = " | ".join(str(c[1]) for c in Layout.calls if c[0] == "label")
    return {"no_model": " | ".join(str(c[1]) for c in no_model), "with_model": [c[1] for c in with_model],
            "prefs_labels": labels,
            "prefs_ops": [c[1] for c in Layout.calls if c[0] == "operator"],
            "addon_prefs": type(addon_prefs).__name__}


@step("site_packages_pref")
def _():
    folder = os.path.join(work, "other_env_site")
    os.makedirs(os.path.join(folder, "pointgt_probe_env"), exist_ok=True)
    with open(os.path.join(folder, "pointgt_probe_env", "__init__.py"), "w") as fh:
        fh.write("VALUE = 7\n")
    prefs = bpy.context.preferences.addons[PKG].preferences
    prefs.site_packages = folder  # the update callback puts it on sys.path
    value = importlib.import_module("pointgt_probe_env").VALUE
    on_path = folder in sys.path
    prefs.site_packages = ""
    return {"value": value, "on_path": on_path, "removed": folder not in sys.path}


@step("degenerate_lattice")
def _():
    pgt = importlib.import_module(PKG + ".core.modelfile.pgt")  # the vendored core, as the add-on uses it
    out = {}
    for name, xyz in (("flat", np.c_[np.random.default_rng(0).uniform(-1, 1, (20, 2)), np.zeros(20)]),
                      ("single", np.array([[0.3, -0.2, 1.5]]))):
        path = os.path.join(work, f"{name}.pgt")
        pgt.save_pgt(path, {"points/xyz": xyz.astype(np.float32)}, {})
        bpy.ops.pointgt.import_model(filepath=path)
        obj = bpy.context.active_object
        rest, _ = evaluated(obj)
        bpy.ops.pointgt.add_lattice()
        pos, _ = evaluated(obj)
        scale = list(obj.modifiers["PointGT Lattice"].object.scale)
        out[name] = {"finite": bool(np.isfinite(pos).all()), "err": float(np.abs(pos - rest).max()),
                     "scale_ok": all(np.isfinite(scale)) and min(scale) > 0, "atlas": obj.pointgt.atlas is None}
    return out


@step("envelope_outside")
def _():
    rig = importlib.import_module(PKG + ".operators.rig")
    bpy.ops.pointgt.import_model(filepath=model)
    obj = bpy.context.active_object
    bpy.ops.object.armature_add(location=(10.0, 0.0, 0.0))  # far away: no point inside its envelope
    arm = bpy.context.active_object
    far = rig.bind_envelopes(obj, arm)
    arm.location = (0.0, 0.0, -1.0)
    bone = arm.data.bones[0]
    bone.head_radius = bone.tail_radius = 0.6
    bone.envelope_distance = 0.5
    bpy.context.view_layer.update()
    cover = rig.envelope_coverage(obj, arm)
    return {"outside_far": far, "outside_near": int((cover <= 0).sum())}


@step("install_offline_wheel")
def _():
    res = bpy.ops.pointgt.install_torch(synchronous=True, requirement="pointgt-probe", index_url="",
                                        find_links=wheels)
    probe = importlib.import_module("pointgt_probe")
    site = importlib.import_module(PKG + ".ui.preferences").user_site_dir(create=False)
    return {"result": sorted(res), "value": probe.VALUE, "in_site": probe.__file__.startswith(site)}


@step("torch_unblocked")
def _():
    sys.meta_path.remove(BLOCKER)
    bpy.ops.pointgt.check_dependencies()
    obj = bpy.data.objects[R["import"]["name"]]
    make_active(obj)
    res = bpy.ops.pointgt.check_device()
    obj.pointgt.device = 'CUDA'
    import torch
    cuda_err = "" if torch.cuda.is_available() else op_error(bpy.ops.pointgt.check_device)
    return {"result": sorted(res), "cuda_err": cuda_err}


@step("occlusion_setting")
def _():
    bpy.ops.pointgt.import_model(filepath=model)
    obj = bpy.context.active_object
    si = importlib.import_module(PKG + ".scene.scene_inputs")
    dg = bpy.context.evaluated_depsgraph_get()
    default = si.object_inputs(obj, dg).occlusion
    obj.pointgt.occlusion = False
    off = si.object_inputs(obj, bpy.context.evaluated_depsgraph_get()).occlusion
    return {"default": default, "off": off}


R.pop("_arm", None)
print("RESULTS: " + json.dumps(R))
