"""Benchmark of the Blender add-on's data paths (bpy, CPU): .pgt import, reading deformed points, export.

    .venv/bin/python -m tools.bench.addon --points 200000 --atlas 1024

Registers the add-on from this checkout (not the zip) in Blender-as-a-module, imports a synthetic model,
binds it to a one-bone armature (envelopes), then times `evaluated_points` per posed frame and one export.
Prints a small table; docs/addon.md quotes it.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--atlas", type=int, default=1024, help="atlas side in texels")
    ap.add_argument("--frames", type=int, default=10)
    args = ap.parse_args(argv)

    import bpy

    import pointgt_blender
    from core.modelfile.pgt import save_pgt
    from pointgt_blender.scene.evaluated import evaluated_points

    rng = np.random.default_rng(0)
    tmp = Path(tempfile.mkdtemp(prefix="pointgt-bench-addon-"))
    model = tmp / "bench.pgt"
    save_pgt(model, {"points/xyz": rng.uniform(-0.5, 0.5, (args.points, 3)).astype(np.float32),
                     "atlas/image": rng.uniform(0, 1, (args.atlas, args.atlas, 3)).astype(np.float32)}, {})
    pointgt_blender.register()
    rows = []

    t = time.perf_counter()
    assert bpy.ops.pointgt.import_model(filepath=str(model), pack_model=False, add_proxy=False,
                                        check_blank=False) == {'FINISHED'}
    rows.append(("import .pgt (read + mesh + packed atlas)", time.perf_counter() - t))
    obj = bpy.context.active_object
    t = time.perf_counter()
    assert bpy.ops.pointgt.pack_model() == {'FINISHED'}
    rows.append(("pack the model into the .blend (read + SHA-256)", time.perf_counter() - t))

    bpy.ops.object.armature_add(location=(0.0, 0.0, -1.0))
    arm = bpy.context.active_object
    arm.data.bones[0].head_radius = arm.data.bones[0].tail_radius = 0.8
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.pointgt.bind_armature(mode='ENVELOPE', armature=arm.name) == {'FINISHED'}
    pb = arm.pose.bones[0]
    pb.rotation_mode = 'XYZ'
    times = []
    for frame in range(args.frames):
        pb.rotation_euler = (0.05 * frame, 0.0, 0.0)
        t = time.perf_counter()
        bpy.context.view_layer.update()
        pos, ids = evaluated_points(obj, bpy.context.evaluated_depsgraph_get())
        times.append(time.perf_counter() - t)
    rows.append((f"pose + evaluate + read positions/ids (median of {args.frames})", float(np.median(times))))

    t = time.perf_counter()
    assert bpy.ops.pointgt.export_deformed(filepath=str(tmp / "posed.npy")) == {'FINISHED'}
    rows.append(("export deformed points (.npy pair, atomic)", time.perf_counter() - t))

    print(f"points {args.points}, atlas {args.atlas}x{args.atlas}, bpy {bpy.app.version_string}")
    for name, sec in rows:
        print(f"{name:<60s} {sec * 1000:8.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
