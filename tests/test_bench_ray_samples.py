"""bench/ray_samples.py: the count of samples that carry a ray's weight (issue 32, item 3)."""

import dataclasses

import torch

from bench.ray_samples import measure, needed_for
from nepf_core.config import tiny
from nepf_core.model import NePFModel
from nepf_core.rays import RayBatch


def test_needed_for_counts_the_largest_weights_to_the_share():
    w = torch.tensor([[0.05, 0.5, 0.15, 0.3],     # sorted: 0.5, 0.3, 0.15, 0.05 (sum 1)
                      [0.0, 0.0, 0.0, 0.0],       # no weight: 0 samples
                      [0.0, 0.2, 0.0, 0.0]])      # one sample holds it all
    assert needed_for(w, 0.99).tolist() == [4, 0, 1]
    assert needed_for(w, 0.8).tolist() == [2, 0, 1]     # 0.5 + 0.3 reaches 0.8
    assert needed_for(w, 0.5).tolist() == [1, 0, 1]


def test_measure_counts_within_the_samples_of_each_kind():
    torch.manual_seed(0)
    cfg = tiny()
    cfg.render.head_weight_threshold = 1e-4
    model = NePFModel(dataclasses.replace(cfg.model, background=True)).eval()
    o = torch.tensor([[0.0, 0.0, -3.0]]).repeat(64, 1)
    d = torch.nn.functional.normalize(torch.randn(64, 3) * 0.1 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    rays = RayBatch(origins=o, directions=d, rgb=torch.zeros(64, 3))
    with torch.no_grad():
        row = measure(model, rays, cfg.render)
    S = cfg.render.n_samples + cfg.render.n_importance
    assert row["object_samples"] == S and row["rays"] == 64
    assert 0 <= row["object_carrying"] <= S and 0 <= row["object_for_99pct"] <= S
    # a sample over 1e-3 is over the heads' 1e-4 threshold: evaluated heads include every carrier
    assert row["head_evals"] >= row["object_carrying"]
    assert 0.0 <= row["object_cover"] <= 1.0 + 1e-6
    # the cover is the renderer's own opacity on the same rays (an independent path through render_rays)
    from nepf_core.render.renderer import render_rays
    with torch.no_grad():
        out = render_rays(model, rays, cfg.render, train=False)
    assert abs(row["object_cover"] - float(out.weight_sum.mean())) < 1e-5
    n = model.background.cfg.n_samples
    assert row["background_samples"] == n
    assert 0 <= row["background_carrying"] <= n and 0 <= row["background_for_99pct"] <= n
