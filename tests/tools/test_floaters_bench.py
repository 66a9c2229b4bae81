"""tools.bench.floaters on a tiny card model: the rows it scores and that removing a speck restores the model."""
import math

import torch

from core.bundle import save_bundle
from tests.helpers.synthetic import write_split
from tests.helpers.tiny import tiny_bundle
from tools.bench.floaters import floater_rows, markdown


def test_rows_remove_an_added_speck_and_score_the_model_without_it(tmp_path):
    bundle, _, test = tiny_bundle("fast")
    data = write_split(tmp_path / "card", test)
    clean = save_bundle(tmp_path / "clean.pgt", bundle, backup=False)
    m = bundle.model
    toward = test.c2w[0, :3, 3] * 0.5  # halfway to the first test camera, where it sees them
    speck = toward + torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    with torch.no_grad():
        m.xyz = torch.nn.Parameter(torch.cat([m.xyz.detach(), speck]))
        m.features = torch.nn.Parameter(torch.cat([m.features.detach(), m.features.detach()[:3]]))
        m.influence = torch.nn.Parameter(torch.cat([m.influence.detach(), torch.full((3,), 5.0)]))
    specked = save_bundle(tmp_path / "specked.pgt", bundle, backup=False)
    rows = floater_rows(specked, data, [20], [3.0], log=lambda *_: None)
    base = floater_rows(clean, data, [20], [3.0], log=lambda *_: None)
    assert [(r["size"], r["radius"]) for r in rows] == [(0, 0.0), (20, 3.0)]
    assert rows[0]["removed"] == 0 and rows[0]["points"] == base[0]["points"] + 3
    assert rows[1]["removed"] == base[1]["removed"] + 3
    assert all(math.isfinite(r["psnr"]) and math.isfinite(r["psnr_object"]) for r in rows)
    assert rows[1]["psnr"] == base[1]["psnr"]  # the same points remain: the same frames
    assert rows[0]["psnr"] < rows[1]["psnr"]  # the speck showed
    table = markdown(rows).splitlines()
    assert len(table) == 3 and table[2].startswith("| card |") and f"{rows[1]['removed']}, +" in table[2]
