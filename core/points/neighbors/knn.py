"""The k nearest other points of each point of a cloud, in 3-D (the canonical neighbourhoods of
core/edits/deformation.py, the floater search of core/points/floaters.py): a scipy k-d tree on CPU tensors, chunked
brute force elsewhere (or without scipy); both exact."""
from __future__ import annotations

import math

import torch


def point_knn(points: torch.Tensor, k: int, chunk: int = 2048) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest other points of each point (self excluded): points [N, 3] finite -> (idx [N, k] int64 with -1
    where N - 1 < k, dist [N, k] float32 with +inf there)."""
    n = points.shape[0]
    kk = min(k, max(n - 1, 0))
    idx = torch.full((n, k), -1, dtype=torch.long, device=points.device)
    dist = torch.full((n, k), math.inf, dtype=torch.float32, device=points.device)
    if kk == 0:
        return idx, dist
    try:
        from scipy.spatial import cKDTree  # heavy import kept local

        if points.device.type != "cpu":
            raise ImportError
        p = points.detach().double().numpy()
        d, i = cKDTree(p).query(p, kk + 1)
        i, d = torch.from_numpy(i.reshape(n, -1)), torch.from_numpy(d.reshape(n, -1))
        # drop the point itself (the first column unless duplicates tie with it)
        self_col = i == torch.arange(n)[:, None]
        keep = ~self_col
        keep[:, -1] &= self_col.any(1)  # no self found (ties): drop the farthest instead
        i = i[keep].view(n, kk)
        d = d[keep].view(n, kk)
    except ImportError:
        parts_i, parts_d = [], []
        for s in range(0, n, chunk):
            dd = torch.cdist(points[s:s + chunk].double(), points.double())
            dd[torch.arange(dd.shape[0]), torch.arange(s, s + dd.shape[0])] = math.inf
            v, j = dd.topk(kk, dim=1, largest=False)
            parts_i.append(j)
            parts_d.append(v)
        i, d = torch.cat(parts_i).cpu(), torch.cat(parts_d).cpu()
    idx[:, :kk] = i.to(points.device)
    dist[:, :kk] = d.to(points.device, torch.float32)
    return idx, dist
