"""Benchmark of the neighbour search: brute force (backend "torch") vs the fast paths, measured in the same run.

Run: `python -m tools.bench.neighbors` (defaults: 128×128 pixel rays of one camera × 10k points on a noisy unit
sphere that fills ~60 % of the frame, K = 20). Prints the machine, one row per metric and search (median seconds
over the repeats), how many rays got the same neighbour set from both paths, and how many rays found a neighbour.

Rows: the uncapped searches (brute force vs the k-d tree, backend "kdtree"), then the capped screen searches the
model uses by default (brute force with the same pixel radius cap vs the compiled grid, backend "compiled", when
numba is installed, and the pure-torch pixel grid, backend "grid").
"""
from __future__ import annotations

import argparse
import math
import statistics
import time

from tools.machine import machine_line


def _median_time(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def _same_sets(a, b, rtol: float = 1e-4) -> float:
    """Fraction of rays whose neighbour sets agree, where members tied with the K-th distance may differ."""
    import torch

    fin = torch.isfinite(b.dist)
    kth = b.dist.masked_fill(~fin, -math.inf).max(dim=1, keepdim=True).values
    sure = fin & (b.dist < kth - rtol * (1 + kth.abs()))
    member = (b.idx[:, :, None] == a.idx[:, None, :]).any(-1)
    ok = (member | ~sure).all(1) & (a.valid.sum(1) == b.valid.sum(1))
    return float(ok.float().mean())


def sphere_scene(n: int, size: int, seed: int):
    """n points on a noisy unit sphere and a camera (NeRF-synthetic field of view) at distance 3.3, where the
    sphere covers ~60 % of a size × size frame. Returns points [n, 3], c2w [4, 4], focal, query_px [size², 2]."""
    import torch

    from core.images.cameras import focal_from_fov, look_at

    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=g)
    pts = pts / pts.norm(dim=1, keepdim=True) * (1 + 0.01 * torch.randn(n, 1, generator=g))
    eye = torch.tensor([2.4, -2.9, 1.6])
    c2w = look_at((eye * 3.3 / eye.norm()).tolist()).float()
    focal = focal_from_fov(size, 0.6911)
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    q = torch.stack([cols.flatten() + 0.5, rows.flatten() + 0.5], -1).float()
    return pts, c2w, focal, q


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=10_000)
    ap.add_argument("--size", type=int, default=128, help="image is size × size pixels, one ray per pixel")
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=7, help="repeats of the fast path (median reported)")
    ap.add_argument("--brute-repeats", type=int, default=3, help="repeats of the brute force (median reported)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", choices=["all", "capped", "uncapped"], default="all", help="which rows to run")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch threads for the brute force and the k-d tree path (0 = torch's default); both grids "
                         "(compiled and torch) always run on one thread")
    args = ap.parse_args(argv)

    import torch

    if args.threads > 0:
        torch.set_num_threads(args.threads)

    from core.images.cameras import pixel_rays
    from core.points.neighbors import compiled
    from core.points import neighbors as nb

    pts, c2w, focal, q = sphere_scene(args.points, args.size, args.seed)
    h = w = args.size
    o, d = pixel_rays(c2w, h, w, focal)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    inf = math.inf

    def screen(depth_factor, cap):
        return lambda b: nb.screen_knn(pts, c2w, h, w, focal, q, args.k, depth_factor, backend=b, max_radius_px=cap)

    rows = []  # (metric, cap label, call, fast backend)
    if args.only in ("all", "uncapped"):
        rows += [("perpendicular", "none", lambda b: nb.rays_knn_perpendicular(pts, o, d, args.k, backend=b), "kdtree"),
                 ("screen", "none", screen(False, inf), "kdtree"),
                 ("screen_depth", "none", screen(True, inf), "kdtree")]
    cap = nb.ScreenIndex(pts, c2w, h, w, focal).radius_px(args.k)
    if args.only in ("all", "capped"):
        fast = ["compiled"] if compiled.available() else []
        for b in fast + ["grid"]:  # compiled (numba) grid first: the CPU default when numba is installed
            rows += [("screen", f"auto = {cap:.2f} px", screen(False, "auto"), b),
                     ("screen_depth", f"auto = {cap:.2f} px", screen(True, "auto"), b)]
    print(machine_line())
    print(f"scene: {h}x{w} = {h * w} rays of one camera, {args.points} points on a unit sphere covering ~60 % of the "
          f"frame, K = {args.k}; median of {args.brute_repeats} (brute) / {args.repeats} (fast) runs")
    print("| metric | radius cap | brute force (torch) s | fast path s | speed-up | rays with equal sets "
          "| rays with ≥ 1 / K neighbours |")
    print("|---|---|---|---|---|---|---|")
    for name, cap_label, call, fast in rows:
        call(fast)  # warm-up: imports, allocator
        t_brute, ref = _median_time(lambda: call("torch"), args.brute_repeats)
        t_fast, got = _median_time(lambda: call(fast), args.repeats)
        hit = float(got.valid[:, 0].float().mean())
        full = float(got.valid[:, -1].float().mean())
        print(f"| {name} | {cap_label} | {t_brute:.3f} | {t_fast:.4f} ({fast}) | {t_brute / t_fast:.0f}x "
              f"| {_same_sets(got, ref):.4f} | {hit:.3f} / {full:.3f} |", flush=True)


if __name__ == "__main__":
    main()
