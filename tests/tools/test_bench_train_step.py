"""tools.bench.train_step: a timed fit reports every part, and the core functions it wrapped are restored."""
import torch

import core.points.train as tr
from core.points.model import PointModel
from core.points.train import TrainConfig
from tests.helpers.synthetic import fibonacci_cameras, render_split
from tests.helpers.tiny import model_config
from tools.bench.train_step import PARTS, time_fit


def test_time_fit_reports_parts_and_restores_the_wrapped_functions():
    split = render_split("sphere", fibonacci_cameras(2, seed=3), 24)
    before = (PointModel.attend, tr.select_neighbors, tr.evaluate, torch.Tensor.backward, torch.optim.Adam.step)
    for path in ("torch", "chunked"):
        cfg = TrainConfig(steps=4, patches=1, patch_size=16, eval_every=1e9, eval_views=1, device="cpu", threads=1,
                          key_path=path)
        res = time_fit(split, split, model_config("card", num_points=300, decoder="unet"), cfg)
        assert res["steps"] == 4 and res["cpu_per_step"] > 0 and res["wall_per_step"] > 0
        assert set(res["parts"]) == set(PARTS)
        for part in ("search", "attend", "decoder", "backward", "adam"):
            assert res["parts"][part] > 0, part
    assert before == (PointModel.attend, tr.select_neighbors, tr.evaluate, torch.Tensor.backward,
                      torch.optim.Adam.step)


def test_time_fit_measures_the_workers_critical_path():
    import core.util.workers as workers

    split = render_split("sphere", fibonacci_cameras(2, seed=3), 24)
    before = workers.run
    cfg = TrainConfig(steps=3, patches=2, patch_size=16, eval_every=1e9, eval_views=1, device="cpu", threads=2,
                      workers=2)
    res = time_fit(split, split, model_config("card", num_points=300, decoder="unet"), cfg)
    assert res["pieces_per_step"] > 0  # the rays and the decoder's patches ran on the workers
    assert res["cpu_per_step"] < res["critical_per_step"] < res["cpu_per_step"] + res["pieces_per_step"]
    assert workers.run is before
