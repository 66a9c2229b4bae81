"""The torch side of the add-on: torch detection, model/state caches, frame compositing, paint transfer.

No bpy here: these modules take plain arrays and run (and are tested) without Blender."""
