"""Reading and writing Blender data: evaluated points, scene inputs, cameras, proxy meshes, packed models,
atlas images, the add-on's in-memory state and the Blender handlers."""
