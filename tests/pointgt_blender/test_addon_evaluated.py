"""Checks on deformed points before they reach the renderer (no Blender needed)."""
from __future__ import annotations

import numpy as np
import pytest

from core.util.errors import InputError
from pointgt_blender.scene.evaluated import check_points, to_world


def test_missing_ids_with_same_count_become_identity():
    ids = check_points("obj", np.zeros((4, 3), np.float32), None, 4)
    assert ids.dtype == np.int64 and ids.tolist() == [0, 1, 2, 3]


def test_count_change_without_ids_is_an_error():
    with pytest.raises(InputError, match="from 4 to 6 and dropped the 'pointgt_id'"):
        check_points("obj", np.zeros((6, 3), np.float32), None, 4)


def test_count_change_with_ids_is_fine_duplicates_allowed():
    ids = check_points("obj", np.zeros((3, 3), np.float32), np.array([2, 2, 0]), 4)
    assert ids.tolist() == [2, 2, 0]


def test_nonfinite_positions_name_the_point_ids():
    pos = np.zeros((8, 3), np.float32)
    pos[[2, 5], 1] = [np.nan, np.inf]
    with pytest.raises(InputError, match=r"2 of 8 deformed points are NaN or infinite \(ids 12, 15\)"):
        check_points("obj", pos, np.arange(10, 18), 20)


def test_ids_outside_the_model_and_empty_results_are_errors():
    with pytest.raises(InputError, match=r"0\.\.3"):
        check_points("obj", np.zeros((2, 3), np.float32), np.array([0, 4]), 4)
    with pytest.raises(InputError, match="no points left"):
        check_points("obj", np.zeros((0, 3), np.float32), np.zeros(0, np.int64), 4)


def test_to_world_matches_homogeneous_reference():
    rng = np.random.default_rng(1)
    mat = rng.normal(size=(4, 4))
    mat[3] = [0, 0, 0, 1]
    pts = rng.normal(size=(9, 3)).astype(np.float32)
    ref = (np.c_[pts, np.ones(9)] @ mat.T)[:, :3]
    np.testing.assert_allclose(to_world(pts, mat), ref, rtol=1e-5, atol=1e-5)
