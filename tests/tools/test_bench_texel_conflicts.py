"""tools.bench.texel_conflicts: a sheet's samples are clean under a one-to-one map, compression where the map
squeezes the sheet, overlap where it lays a distant part of the sheet onto the same texels."""
import numpy as np

from tools.bench.texel_conflicts import sample_classes


def _sheet(n=6000, seed=0):
    g = np.random.default_rng(seed)
    return np.c_[g.uniform(0, 1, n), g.uniform(0, 0.5, n), 1e-4 * g.standard_normal(n)]


def test_one_to_one_compressing_and_overlapping_maps_are_told_apart():
    y = _sheet()
    spacing = float(np.sqrt(0.5 / len(y)))
    chart = np.zeros(len(y), np.int64)
    clean = sample_classes(y, y[:, :2] / spacing, chart, spacing)             # one texel per spacing
    assert (clean == 0).mean() > 0.99
    squeezed = np.c_[y[:, 0] / (8 * spacing), y[:, 1] / spacing]              # 8 spacings per texel along x
    comp = sample_classes(y, squeezed, chart, spacing)
    assert (comp == 1).mean() > 0.5 and (comp == 2).mean() < 0.02
    # the map folds the sheet's right half back onto its left half with the same orientation (a shift)
    t = np.c_[np.where(y[:, 0] < 0.5, y[:, 0], y[:, 0] - 0.5), y[:, 1]] / spacing
    over = sample_classes(y, t, chart, spacing)
    assert (over == 2).mean() > 0.3 and (over == 1).mean() < 0.05
    # the same shift into a chart of its own: clean again
    split = sample_classes(y, t, (y[:, 0] >= 0.5).astype(np.int64), spacing)
    assert (split == 0).mean() > 0.99
