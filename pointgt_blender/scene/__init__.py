"""Reading and writing Blender data: evaluated points, scene inputs, cameras, proxy meshes, packed models,
atlas images, the session state and the Blender handlers."""
