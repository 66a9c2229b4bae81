"""Where an atlas's baked retexture goes wrong at its own surface samples: texels shared by distant places.

`python -m tools.bench.texel_conflicts --model M.pgt --scene DIR [--texture stripes]`: bakes the retexture (the
scene's procedural texture, as `pointgt eval-edits` bakes it) into the model's atlas, looks it up at the atlas's
stored surface samples and splits the squared error there (against the texture at the sample) by what the sample's
texel holds. A texel is *shared* when a sample of the same layout chart in it lies more than 3 sample spacings away
along the surface (in the tangent plane of the first sample's 48-neighbour normal); a shared sample is
*compression* when the map's local linear part (least squares over its 16 nearest samples) would put every such
far sample within 3 texels of it (the map squeezes the surface there), else *overlap* (the map came back to this
texel from another place). Separately, *clamped*: samples whose chart coordinates lie more than 2 texels from any
texel their chart's islands hold (a lookup clamps them onto an island's border). Per class: the samples' share,
mean squared error and share of the total squared error.
"""
from __future__ import annotations

import numpy as np
import torch

from tools.bench import parse, parser, write_json

CLASSES = ("clean", "compression", "overlap")


def sample_classes(y: np.ndarray, t: np.ndarray, chart: np.ndarray, spacing: float, far: float = 3.0,
                   texels: float = 3.0) -> np.ndarray:
    """Class of every sample [S] (0 clean, 1 compression, 2 overlap; module doc): positions y [S, 3], texel
    coordinates t [S, 2] within its layout chart chart [S]."""
    from scipy.spatial import cKDTree

    from core.atlas.fit import sample_normals
    from core.atlas.pieces import solve_columns

    normals = sample_normals(y, 48)
    _, nb = cKDTree(y).query(y, k=min(16, len(y)))
    D, T = y[nb] - y[:, None], t[nb] - t[:, None]
    jac = solve_columns(np.einsum("mki,mkj->mij", D, D) + 1e-12 * np.eye(3), np.einsum("mki,mkj->mij", D, T))
    cell = np.floor(t).astype(np.int64)
    key = (chart.astype(np.int64) * (cell[:, 1].max() + 2) + cell[:, 1]) * (cell[:, 0].max() + 2) + cell[:, 0]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    starts = np.r_[0, np.nonzero(np.diff(ks))[0] + 1]
    ends = np.r_[starts[1:], len(ks)]
    out = np.zeros(len(y), np.int64)
    for s0, e0 in zip(starts, ends):
        if e0 - s0 < 2:
            continue
        idx = order[s0:e0]
        n = normals[idx[0]]
        d = y[idx][:, None] - y[idx][None]
        d = d - (d @ n)[..., None] * n
        dist = np.linalg.norm(d, axis=-1)
        if dist.max() <= far * spacing:
            continue
        for a, i in enumerate(idx):
            far_ones = dist[a] > far * spacing
            if far_ones.any():
                pred = np.linalg.norm(-d[a, far_ones] @ jac[i], axis=-1)
                out[i] = max(out[i], 2 if (pred > texels).any() else 1)
    return out


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--model", required=True, help="model file with an island atlas (.pgt)")
    ap.add_argument("--scene", required=True, help="its scene folder (pointgt make-scene): the texture's box")
    ap.add_argument("--texture", default="stripes", help="procedural retexture (core/edits/procedural.py)")
    args = parse(ap, argv)
    from core.atlas.fit import sample_spacing
    from core.atlas.packing import chart_coords
    from core.bundle import load_bundle
    from core.edits.bake import bake
    from core.edits.procedural import evaluate
    from core.util.errors import InputError
    from tools.scenes.spec import load_scene_spec

    atlas = load_bundle(args.model, "cpu").atlas
    if atlas is None or not atlas.islands or atlas.bake_samples is None:
        raise InputError(f"{args.model}: needs an island atlas with its surface samples (`pointgt atlas`)")
    spec = load_scene_spec(args.scene)
    c, h, params = spec["bbox"]["center"], spec["bbox"]["half_size"], spec["texture"]["params"]

    def fn(p):
        return evaluate(args.texture, p, c, h, params.get(args.texture))[0], None

    S = atlas.bake_samples
    y = atlas.on_surface(S).numpy().astype(np.float64)
    spacing = float(sample_spacing(y)[0])
    probs, uv = atlas.chart_uv(S, placed=False)
    chart = atlas.layout.hard_probs(probs).argmax(-1)
    aff = atlas.layout.affine[chart]
    t = ((aff[:, :, :2] @ chart_coords(uv, chart)[..., None])[..., 0] + aff[:, :, 2]).numpy()
    chart = chart.numpy()
    with torch.no_grad():
        err = ((atlas.lookup(S, bake(atlas, fn)) - fn(S)[0]) ** 2).sum(-1).numpy()
    cls = sample_classes(y, t, chart, spacing)
    G = atlas.layout.cells.shape[1]
    k = np.floor(t).astype(np.int64).clip(0, G - 1)
    near = atlas.layout.nearest_cells(torch.from_numpy(chart), torch.from_numpy(k[:, 1]),
                                      torch.from_numpy(k[:, 0])).numpy()
    clamped = np.hypot(near[:, 0] - t[:, 1] + 0.5, near[:, 1] - t[:, 0] + 0.5) > 2.0
    total = max(float(err.sum()), 1e-30)
    out = {"model": str(args.model), "samples": int(len(S)), "spacing": spacing, "mse": float(err.mean())}
    for name, m in [*((n, cls == i) for i, n in enumerate(CLASSES)), ("clamped", clamped)]:
        out[name] = {"share": float(m.mean()), "mse": float(err[m].mean()) if m.any() else 0.0,
                     "error_share": float(err[m].sum()) / total}
        print(f"{name:12s} samples {100 * out[name]['share']:5.1f} %  mse {out[name]['mse']:.4f}  "
              f"share of the squared error {100 * out[name]['error_share']:5.1f} %")
    print(f"all          {len(S)} samples, mse {out['mse']:.4f}")
    write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
