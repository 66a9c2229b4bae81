"""A tiny trained model (stage 1 + stage 2) on the analytic card scene, for edit/render tests (seconds)."""
from __future__ import annotations

import functools

import torch

from core.atlas.config import AtlasConfig
from core.bundle import Bundle
from core.pipeline import fit_atlas_stage
from core.points.model import ModelConfig
from core.points.train import TrainConfig, fit_points
from tests.helpers.synthetic import fibonacci_cameras, render_split

SIZE = 40


@functools.lru_cache(maxsize=None)
def tiny_card(shape: str = "card", steps: int = 200, atlas_steps: int = 200,
              decoder: str = "none") -> tuple[Bundle, object, object]:
    """(bundle with atlas, train split, test split); decoder "none" | "unet". Cached per process: treat the
    result as read-only."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread is faster, and far faster on a busy machine
    try:
        return _train(shape, steps, atlas_steps, decoder)
    finally:
        torch.set_num_threads(threads)


def _train(shape: str, steps: int, atlas_steps: int, decoder: str):
    torch.manual_seed(0)
    train = render_split(shape, fibonacci_cameras(12, seed=0), SIZE)
    test = render_split(shape, fibonacci_cameras(4, seed=5), SIZE, split="test")
    mcfg = ModelConfig(num_points=1000, k=8, feature_dim=16, key_width=32, value_width=32, decoder=decoder)
    tcfg = TrainConfig(steps=steps, patches=2, patch_size=20, eval_every=1e9, eval_views=2, device="cpu",
                       prune_every=0, clone_every=0, reg_start=0.3)
    model, _ = fit_points(train, test, mcfg, tcfg, show_progress=False)
    model.eval()
    bundle = Bundle(model=model, meta={"scene": {"name": shape}})
    fit_atlas_stage(bundle, train, AtlasConfig(steps=atlas_steps, texture_steps=60, charts="4", device="cpu"),
                    show_progress=False)
    return bundle, train, test
