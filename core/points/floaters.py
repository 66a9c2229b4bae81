"""Floaters: small clusters of points apart from the rest of a fitted cloud.

A fit can leave a few points hanging in front of the object where every training view sees them against the object
itself (their colour matches what lies behind them there, so no training image pulls them back); from a new view
they show as specks over the background. A floater is a point in a connected group of fewer than `max_size` points
that lies farther than `radius` × the cloud's spacing (the median distance from a point to its nearest other
point) from every point outside the group; groups are the connected components of the graph that joins two points
closer than that. With each point's `max_size` nearest neighbours as the graph's candidate edges the test is
exact: a point of a group smaller than `max_size` has at least one point outside the group among them, the nearest
such one first. `python -m tools.bench.floaters` measures what removing them does on fitted models.
"""
from __future__ import annotations

import torch

from core.points.neighbors.knn import point_knn


def components(idx: torch.Tensor, edge: torch.Tensor) -> torch.Tensor:
    """Connected components of a graph given as neighbour lists: idx [N, k] int64 (-1 = none), edge [N, k] bool
    (which of them are edges; undirected). Returns labels [N] int64: each point's component's smallest index."""
    n = idx.shape[0]
    lab = torch.arange(n, device=idx.device)
    keep = edge & (idx >= 0)
    src = torch.arange(n, device=idx.device)[:, None].expand_as(idx)[keep]
    dst = idx[keep]
    if src.numel() == 0:
        return lab
    while True:  # min-label propagation along the edges, both ways, with pointer jumping
        m = torch.minimum(lab[src], lab[dst])
        new = lab.clone()
        new.scatter_reduce_(0, src, m, reduce="amin")
        new.scatter_reduce_(0, dst, m, reduce="amin")
        new = new[new]
        if torch.equal(new, lab):
            return lab
        lab = new


@torch.no_grad()
def floater_mask(xyz: torch.Tensor, max_size: int = 20, radius: float = 3.0, max_share: float = 0.1
                 ) -> torch.Tensor:
    """Which points are floaters (module doc): xyz [N, 3] -> mask [N] bool.

    max_size: groups of fewer points than this are floaters; radius: the gap, in spacings, that separates a group;
    max_share: when the floaters would be more than this share of the points, none is (the cloud is not one surface
    with a few specks: a sparse or broken fit, which removing points would not mend). Non-finite points are never
    floaters and never anyone's neighbour."""
    n = xyz.shape[0]
    out = torch.zeros(n, dtype=torch.bool, device=xyz.device)
    fin = torch.isfinite(xyz).all(1)
    pts = xyz.detach()[fin]
    m = pts.shape[0]
    if m <= max_size or max_size < 2 or not radius > 0:
        return out
    idx, dist = point_knn(pts, int(max_size))
    nearest = dist[:, 0]
    spacing = float(nearest[torch.isfinite(nearest)].median()) if bool(torch.isfinite(nearest).any()) else 0.0
    if not spacing > 0:  # duplicated points everywhere: no length scale to call a gap
        return out
    lab = components(idx, dist < radius * spacing)
    size = torch.bincount(lab, minlength=m)[lab]
    small = size < max_size
    if float(small.sum()) > max_share * m:
        return out
    out[fin.nonzero().squeeze(1)] = small
    return out
