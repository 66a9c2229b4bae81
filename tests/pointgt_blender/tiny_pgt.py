"""A tiny trained PointGT model (stage 1 + atlas) of the analytic card for the add-on tests: about 25 s on one
CPU thread. The card lies in the plane z = 0 (|x| < 0.9, |y| < 0.5); its colour is `synthetic.stripes`."""
from __future__ import annotations

from pathlib import Path

import torch

from core.atlas.config import AtlasConfig
from core.bundle import Bundle, save_bundle
from core.pipeline import fit_atlas_stage
from core.points.model import ModelConfig
from core.points.train import TrainConfig, fit_points
from tests.helpers.synthetic import fibonacci_cameras, render_split

CARD_HALF = (0.9, 0.5)


def train_tiny_card(path: str | Path) -> Path:
    """Train and save the model; returns its path."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the machine is shared: one thread is faster than fighting for two
    try:
        torch.manual_seed(0)
        train = render_split("card", fibonacci_cameras(8, seed=0), 32)
        mcfg = ModelConfig(num_points=600, k=8, feature_dim=8, key_width=16, value_width=16, key_freqs=2)
        tcfg = TrainConfig(steps=300, patches=1, patch_size=32, eval_every=1e9, eval_views=1, device="cpu",
                           prune_every=0, clone_every=0, reg_start=0.3, seed=0)
        model, _ = fit_points(train, train, mcfg, tcfg, show_progress=False)
        model.eval()
        bundle = Bundle(model=model, meta={"scene": {"name": "card"}})
        fit_atlas_stage(bundle, train, AtlasConfig(steps=600, texture_steps=100, charts="4", device="cpu",
                                                   texture_res=32, width_map=64, width_chart=16, depth_map=3,
                                                   depth_chart=2), show_progress=False)
        return save_bundle(path, bundle, backup=False)
    finally:
        torch.set_num_threads(threads)
