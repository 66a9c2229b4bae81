"""Save / load checks shared by the atlas tests whose charts read an analytic texture-coordinate map."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.util.errors import ModelFileError


def check_saves_and_loads_bit_for_bit(atlas: Atlas, xyz: torch.Tensor, tex_map, corrupt_key: str,
                                      corrupt_value: np.ndarray) -> dict:
    """Write `atlas` to arrays and read it back: its analytic map tex_map has no weights, so a network's are
    stored and tex_map is put back after loading. Chart outputs and lookups at xyz [M, 3] must agree bit for bit;
    the arrays with corrupt_key set to corrupt_value, and without corrupt_key, must be refused. Returns the meta."""
    arrays, meta = atlas.to_arrays(), atlas.meta()
    arrays.update({k: v for k, v in Atlas(1, 16, 2, torch.zeros(3), 1.0).to_arrays().items() if "/net/tex." in k})
    loaded = Atlas.from_arrays(arrays, meta)
    loaded.tex = tex_map
    p0, uv0 = atlas.chart_uv(xyz)
    p1, uv1 = loaded.chart_uv(xyz)
    assert torch.equal(p0, p1) and torch.equal(uv0, uv1)
    assert torch.equal(atlas.lookup(xyz), loaded.lookup(xyz))
    bad = dict(arrays)
    bad[corrupt_key] = corrupt_value
    with pytest.raises(ModelFileError):
        Atlas.from_arrays(bad, meta)
    del bad[corrupt_key]
    with pytest.raises(ModelFileError):
        Atlas.from_arrays(bad, meta)
    return meta
