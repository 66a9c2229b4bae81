"""Benchmark of the neighbour search: brute force (backend "torch") vs the k-d tree fast path, same run.

Run: `python -m tools.bench.neighbors` (defaults: 128×128 rays of one camera × 10k points on a noisy unit sphere,
K = 20). Prints the machine, one row per metric (median seconds over the repeats) and how many rays got the
same neighbour set from both paths.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


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
    ok = (member | ~sure).all(1) & torch.equal(a.valid.sum(1), b.valid.sum(1))
    return float(ok.float().mean())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=10_000)
    ap.add_argument("--size", type=int, default=128, help="image is size × size pixels, one ray per pixel")
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=5, help="repeats of the fast path (median reported)")
    ap.add_argument("--brute-repeats", type=int, default=3, help="repeats of the brute force (median reported)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    import torch

    from core.images.cameras import focal_from_fov, look_at, pixel_rays
    from core.points import neighbors as nb

    g = torch.Generator().manual_seed(args.seed)
    pts = torch.randn(args.points, 3, generator=g)
    pts = pts / pts.norm(dim=1, keepdim=True) * (1 + 0.01 * torch.randn(args.points, 1, generator=g))
    h = w = args.size
    focal = focal_from_fov(w, 0.6911)  # NeRF-synthetic field of view
    c2w = look_at((2.4, -2.9, 1.6)).float()  # 4.1 units from the centre, as in NeRF-synthetic
    o, d = pixel_rays(c2w, h, w, focal)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    q = torch.stack([cols.flatten() + 0.5, rows.flatten() + 0.5], -1).float()

    calls = {
        "perpendicular": lambda b: nb.rays_knn_perpendicular(pts, o, d, args.k, backend=b),
        "screen": lambda b: nb.screen_knn(pts, c2w, h, w, focal, q, args.k, backend=b),
        "screen_depth": lambda b: nb.screen_knn(pts, c2w, h, w, focal, q, args.k, depth_factor=True, backend=b),
    }
    try:
        load = "%.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        load = "n/a"
    print(f"machine: {_cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{torch.get_num_threads()} torch threads, load average {load}")
    print(f"scene: {h}x{w} = {h * w} rays of one camera, {args.points} points, K = {args.k}; "
          f"median of {args.brute_repeats} (brute) / {args.repeats} (fast) runs")
    print(f"| metric | brute force (torch) s | fast path (k-d tree) s | speed-up | rays with equal sets |")
    print(f"|---|---|---|---|---|")
    for name, call in calls.items():
        call("kdtree")  # warm-up: imports, allocator
        t_brute, ref = _median_time(lambda: call("torch"), args.brute_repeats)
        t_fast, got = _median_time(lambda: call("kdtree"), args.repeats)
        print(f"| {name} | {t_brute:.3f} | {t_fast:.4f} | {t_brute / t_fast:.0f}x | {_same_sets(got, ref):.4f} |",
              flush=True)


if __name__ == "__main__":
    main()
