"""A fresh Blender process opens the saved, posed and painted scene and renders its animation, as
`blender -b posed.blend -a` would; prints one JSON line "RESULTS: {...}". argv after "--": posed.blend"""
import json
import os
import sys

import bpy

blend = sys.argv[sys.argv.index("--") + 1]
# The bpy module starts with factory preferences; the Blender application reads the saved ones (where the
# first script enabled the extension) at startup, as this does.
bpy.ops.wm.read_userpref()
bpy.ops.wm.open_mainfile(filepath=blend)
out = {"enabled": "bl_ext.user_default.pointgt" in bpy.context.preferences.addons,
       "engine": bpy.context.scene.render.engine,
       "model_path": bpy.data.objects["card"].pointgt.model_path}
try:
    bpy.ops.render.render(animation=True)
    out["frames"] = sorted(os.listdir(os.path.join(os.path.dirname(blend), "frames")))
except Exception as exc:
    out["error"] = f"{type(exc).__name__}: {exc}"
print("RESULTS: " + json.dumps(out))
