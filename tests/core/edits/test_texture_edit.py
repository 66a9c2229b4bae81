"""Texture-edit masks, blends and atlas-image validation."""
import pytest
import torch

from core.edits.texture_edit import blend, check_atlas_image, edit_mask
from core.util.errors import InputError


def test_mask_marks_changed_texels_only():
    a = torch.rand(8, 8, 3)
    b = a.clone()
    b[2:4, 5:7] = 1 - b[2:4, 5:7] + 0.05
    m = edit_mask(a, b)
    assert m.sum() == 4 and bool(m[2:4, 5:7].all())
    b2 = a + 0.001  # below the threshold: PNG rounding must not count as paint
    assert edit_mask(a, b2).sum() == 0


def test_blends():
    r = torch.zeros(3, 3)
    t = torch.ones(3, 3)
    m = torch.tensor([0.0, 0.5, 0.96])
    soft = blend(r, t, m, "soft")
    assert torch.allclose(soft[:, 0], m)
    hard = blend(r, t, m, "threshold")
    assert hard[:, 0].tolist() == [0.0, 0.0, 1.0]
    with pytest.raises(InputError):
        blend(r, t, m, "wrong")


def test_atlas_image_checks():
    good = torch.rand(16, 32, 4)
    assert check_atlas_image(good, (16, 32)).shape == (16, 32, 3)
    with pytest.raises(InputError, match="32x16"):
        check_atlas_image(torch.rand(20, 20, 3), (16, 32))
    bad = torch.rand(16, 32, 3)
    bad[0, 0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        check_atlas_image(bad, (16, 32))
    with pytest.raises(InputError, match="RGB"):
        check_atlas_image(torch.rand(16, 32), (16, 32))
