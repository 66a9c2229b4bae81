"""`pointgt export --outlines`: an RGBA overlay of the island outlines the size of the atlas image."""
import numpy as np
import pytest

from core.images.png import read_png
from core.modelfile import save_pgt
from tools.cli import main


def _model(tmp_path, islands: bool):
    img = np.zeros((12, 10, 3), np.float32)
    arrays = {"atlas/image": img, "atlas/texel_points": np.full((12, 10, 3), np.nan, np.float32)}
    if islands:
        cells = -np.ones((2, 6, 6), np.int32)
        cells[0, 1:4, 1:4] = 0   # a 3x3 island of chart 0
        cells[1, 0:2, 0:5] = 1   # a 2x5 island of chart 1
        arrays.update({"atlas/islands/cells": cells, "atlas/islands/offset": np.array([[0, 0], [4, 8]], np.int32)})
    else:
        arrays["atlas/texel_points"][2:5, 2:6] = 0.0
    path = tmp_path / ("i.pgt" if islands else "g.pgt")
    save_pgt(path, arrays, {"atlas": {}}, allow_nonfinite=["atlas/texel_points"])
    return path


@pytest.mark.parametrize("islands", [True, False])
def test_outlines_png_marks_island_borders(tmp_path, islands):
    out = tmp_path / "outlines.png"
    assert main(["export", str(_model(tmp_path, islands)), "--outlines", str(out)]) == 0
    png = read_png(out)
    assert png.shape == (12, 10, 4)
    drawn = png[..., 3] > 0.5
    if islands:
        assert drawn.sum() == 8 + 10  # 3x3 border (8) + 2x5 (all 10 cells are border)
        assert drawn[1, 1] and not drawn[2, 2] and drawn[8, 5] and drawn[9, 8]
    else:
        assert drawn.sum() == 10 and not drawn[3, 3] and drawn[2, 2]
    assert not drawn[0, 9] and np.allclose(png[drawn][:, :3], [1, 0, 1], atol=1 / 255)


def test_outlines_need_an_atlas(tmp_path, capsys):
    path = tmp_path / "p.pgt"
    save_pgt(path, {"points/xyz": np.zeros((3, 3), np.float32)}, {})
    assert main(["export", str(path), "--outlines", str(tmp_path / "o.png")]) != 0
    assert "has no atlas yet" in capsys.readouterr().err and not (tmp_path / "o.png").exists()
