"""A faster tiny trained model (stage 1 + stage 2) for the stability suite: one torch thread, few steps, small
networks and a small atlas. Quality is low but real (trained, not random); the suite checks finiteness and ranges,
not picture quality. Cached per process: treat the result as read-only."""
from __future__ import annotations

import functools

import torch

from core.atlas.config import AtlasConfig
from core.bundle import Bundle
from core.pipeline import fit_atlas_stage
from core.points.model import ModelConfig
from core.points.train import TrainConfig, fit_points
from tests.helpers.synthetic import fibonacci_cameras, render_split

SIZE = 32


@functools.lru_cache(maxsize=None)
def tiny_fast(shape: str = "card", steps: int = 60, atlas_steps: int = 40) -> tuple[Bundle, object, object]:
    """(bundle with atlas, train split, test split) on the analytic scene `shape` (card | sphere)."""
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # a shared CPU: one thread avoids waiting on a busy second core
        torch.manual_seed(0)
        train = render_split(shape, fibonacci_cameras(8, seed=0), SIZE)
        test = render_split(shape, fibonacci_cameras(2, seed=5), SIZE, split="test")
        mcfg = ModelConfig(num_points=600, k=8, feature_dim=8, key_width=16, key_freqs=2, value_width=16)
        tcfg = TrainConfig(steps=steps, patches=2, patch_size=16, eval_every=1e9, eval_views=1, device="cpu",
                           prune_every=0, clone_every=0, reg_start=0.3)
        model, _ = fit_points(train, test, mcfg, tcfg, show_progress=False)
        model.eval()
        bundle = Bundle(model=model, meta={"scene": {"name": shape}})
        acfg = AtlasConfig(steps=atlas_steps, texture_steps=20, charts="4", texture_res=16, pad=2, batch=256,
                           uv_batch=32, distortion_batch=32, width_chart=32, depth_chart=2, width_map=32,
                           depth_map=2, eval_samples=512, log_every=10_000, device="cpu")
        fit_atlas_stage(bundle, train, acfg, show_progress=False)
    finally:
        torch.set_num_threads(threads)
    return bundle, train, test
