"""Read the deformed points of a PointGT object: evaluated positions and ids via foreach_get (no Python loops),
with the checks the renderer needs (finite positions, ids that still match the model)."""
from __future__ import annotations

import numpy as np

from core.util.errors import InputError

ID_ATTRIBUTE = "pointgt_id"  # integer point attribute: the model's point index, carried through deformers


def read_points(mesh) -> tuple[np.ndarray, np.ndarray | None]:
    """Positions [M, 3] float32 (mesh space) and ids [M] int64 (None when the mesh lost the id attribute)."""
    m = len(mesh.vertices)
    pos = np.empty(m * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", pos)
    attr = mesh.attributes.get(ID_ATTRIBUTE)
    if attr is None or attr.domain != 'POINT' or attr.data_type != 'INT' or len(attr.data) != m:
        return pos.reshape(m, 3), None
    ids = np.empty(m, dtype=np.int32)
    attr.data.foreach_get("value", ids)
    return pos.reshape(m, 3), ids.astype(np.int64)


def to_world(positions: np.ndarray, matrix) -> np.ndarray:
    """Apply a 4x4 (mathutils.Matrix or array) to positions [M, 3] -> [M, 3] float32."""
    mat = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    return (positions @ mat[:3, :3].T + mat[:3, 3]).astype(np.float32)


def check_points(name: str, positions: np.ndarray, ids: np.ndarray | None, point_count: int) -> np.ndarray:
    """Validate deformed points against the model's `point_count`; returns ids [M] int64 (identity ids when
    the attribute is gone but the count is unchanged). Raises InputError with what to fix."""
    m = positions.shape[0]
    if ids is None:
        if m != point_count:
            raise InputError(f"object '{name}': a modifier changed the point count from {point_count} to {m} and "
                             f"dropped the '{ID_ATTRIBUTE}' attribute, so the points no longer match the model; "
                             f"remove modifiers that add or delete points, or keep the attribute")
        ids = np.arange(m, dtype=np.int64)
    if m == 0:
        raise InputError(f"object '{name}': no points left after its modifiers; the model cannot be rendered")
    bad = ~np.isfinite(positions).all(axis=1)
    if bad.any():
        where = ", ".join(str(i) for i in ids[bad][:5])
        raise InputError(f"object '{name}': {int(bad.sum())} of {m} deformed points are NaN or infinite "
                         f"(ids {where}{', ...' if bad.sum() > 5 else ''}); check the modifiers (a zero-scale "
                         f"lattice or bone, or a driver) and reset to canonical if needed")
    if point_count > 0 and (ids.min() < 0 or ids.max() >= point_count):
        raise InputError(f"object '{name}': '{ID_ATTRIBUTE}' values must lie in 0..{point_count - 1}, found "
                         f"{int(ids.min())}..{int(ids.max())}; the attribute was edited - re-import the model")
    return ids


def evaluated_points(obj, depsgraph, space: str = 'WORLD') -> tuple[np.ndarray, np.ndarray]:
    """Deformed points of a PointGT object after all its modifiers: positions [M, 3] float32 (world space, or the
    object's own space with space='LOCAL') and ids [M] int64. Raises InputError when they cannot be used."""
    eval_obj = obj.evaluated_get(depsgraph)
    mesh = eval_obj.data
    if mesh is None or not hasattr(mesh, "vertices"):
        raise InputError(f"object '{obj.name}': its modifiers turned it into something other than a mesh; "
                         f"PointGT needs the points as mesh vertices")
    pos, ids = read_points(mesh)
    ids = check_points(obj.name, pos, ids, int(obj.pointgt.point_count))
    if space == 'WORLD':
        pos = to_world(pos, eval_obj.matrix_world)
        if not np.isfinite(pos).all():
            raise InputError(f"object '{obj.name}': its transform makes positions infinite; apply a sane scale")
    return pos, ids
