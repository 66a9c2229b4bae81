"""PointGT core: the torch side of the project. Never imports bpy.

Data flow, one subpackage per stage:
  images/  -> multi-view images and cameras (NeRF-synthetic loader, rays)
  points/  -> PAPR: points, neighbour search, proximity attention, regularizers, training
  atlas/   -> Nuvo-style UV charts, distortion loss, texture, packed atlas, texel -> surface map
  edits/   -> deformation-aware correspondence and texture-edit masks
  frames/  -> rendering canonical / deformed / edited frames, metrics
Support: modelfile/ (the .pgt format), util/ (progress, devices, atomic writes, errors), config.py.
"""
