"""Stage 2 optimisation: fit_atlas(xyz, rgb, cfg) learns the charts, maps and textures from surface samples."""
from __future__ import annotations

import math
import time
from typing import Callable, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree

from core.atlas import losses
from core.atlas.atlas import Atlas, check_points
from core.atlas.config import AtlasConfig
from core.atlas.distortion import distortion_terms, uv_jacobian
from core.atlas.networks import ChartNet, TexCoordNet, fourier_encode
from core.atlas.packing import blend_charts, dilate_unused
from core.atlas.surface import SurfaceProjection
from core.atlas.texture import filled_kernel_texture
from core.images.metrics import psnr
from core.util.device import resolve_device
from core.util.errors import InputError
from core.util.progress import Progress

MIN_SAMPLES = 64


def _local_pca(xyz: np.ndarray, tree: cKDTree, query: np.ndarray, neighbours: int):
    """Principal axes of the `neighbours` + 1 nearest samples of each query point: xyz [S, 3] with its tree,
    query [m, 3] -> (offsets [m, K+1, 3] of those samples from the query point, eigenvalues [m, 3] ascending,
    eigenvectors [m, 3, 3] as columns: the first the direction of least spread, the last two the tangent plane)."""
    _, idx = tree.query(query, k=neighbours + 1)
    nb = xyz[idx] - query[:, None]
    c = nb - nb.mean(1, keepdims=True)
    w, vec = np.linalg.eigh(np.einsum("mki,mkj->mij", c, c))
    return nb, w, vec


def sample_spacing(xyz: np.ndarray, k: int = 8, neighbours: int = 48, max_points: int = 4000,
                   seed: int = 0, per_sample: bool = False):
    """(median nearest-neighbour distance, estimated surface area) of samples xyz [S, 3].

    Area: a disc holding k samples has area pi r_k^2 ~ k / density, so area ~ S pi mean(r_k^2) / k. r_k is
    measured in each sample's tangent plane (PCA of its `neighbours` nearest samples): real samples form a
    slab a few spacings thick (noisy PAPR surface points), where 3-D distances overestimate the area about twice.
    per_sample: also return (sel [m] indices of the measured samples, their area elements [m], summing to the area
    up to rounding) — what `island_layout` and `chart_pieces_step` take as `elements`.
    """
    S = len(xyz)
    k = min(k, S - 1)
    K = min(max(neighbours, k + 1), S - 1)
    tree = cKDTree(xyz)
    d1, _ = tree.query(xyz, k=2)
    sel = np.random.default_rng(seed).permutation(S)[:max_points]
    nb, _, vec = _local_pca(xyz, tree, xyz[sel], K)  # offsets [m, K+1, 3] (row 0 is the sample itself)
    r = np.sort(np.linalg.norm(np.einsum("mki,mij->mkj", nb, vec[:, :, 1:]), axis=-1), axis=1)[:, k]
    spacing, area = float(np.median(d1[:, 1])), float(S * math.pi * np.mean(r ** 2) / k)
    if per_sample:
        return spacing, area, sel, S * math.pi * r ** 2 / k / len(sel)
    return spacing, area


def sample_normals(xyz: np.ndarray, neighbours: int = 256, max_points: int = 20000, seed: int = 0,
                   chunk: int = 2000) -> np.ndarray:
    """Unit surface normal of every sample xyz [S, 3] -> [S, 3] float32: the direction of least spread (PCA) of the
    `neighbours` nearest samples. Real samples form a slab a few spacings thick (PAPR's surface points; on the
    tube of the scene library its spread across is 0.8 of its spread along in a 48-sample neighbourhood), so the
    neighbourhood must be wide: with 48 neighbours the normals of adjacent tube samples disagree (10th percentile
    |cos| 0.44), with 256 they agree (0.98). The PCA runs on at most `max_points` samples (a fixed random subset)
    and every sample takes the normal of the nearest of them. Sign arbitrary (the loss that uses it is even in n);
    zero where the neighbourhood spans no plane."""
    S = len(xyz)
    out = np.zeros((S, 3), np.float32)
    if S < 3:
        return out
    K = min(neighbours, S - 1)
    tree = cKDTree(xyz)
    sel = np.sort(np.random.default_rng(seed).permutation(S)[:max_points])
    normals = np.zeros((len(sel), 3))
    for s in range(0, len(sel), chunk):
        _, w, vec = _local_pca(xyz, tree, xyz[sel[s:s + chunk]], K)
        ok = np.isfinite(vec[:, :, 0]).all(-1) & (w[:, 1] > 1e-30)  # a plane is defined (two directions of spread)
        normals[s:s + chunk][ok] = vec[ok, :, 0]
    _, near = cKDTree(xyz[sel]).query(xyz)
    out[:] = normals[near]
    return out


def pixel_footprint(xyz, centres, focal: float) -> float:
    """World size of one training-image pixel on the surface: median over views of the median camera distance of
    the samples xyz [S, 3], divided by the focal length in pixels. centres [V, 3] camera positions."""
    x = torch.as_tensor(xyz, dtype=torch.float64)
    x = x[torch.linspace(0, len(x) - 1, min(len(x), 20000)).long()]
    d = [float((x - torch.as_tensor(c, dtype=torch.float64)).norm(dim=-1).median()) for c in centres]
    if not d or not focal > 0:
        raise InputError("pixel footprint: need at least one camera and a positive focal length")
    return float(np.median(d)) / float(focal)


def _first_texel_size(probs: torch.Tensor, elements: tuple[np.ndarray, np.ndarray], area: float, R: int,
                      cfg: AtlasConfig, pixel_size: float | None) -> tuple[float, np.ndarray]:
    """The texel size (world units) an island layout tries first, and each chart's world area [n] (samples by
    their most probable chart in probs [S, n]; elements: the samples' (sel, area elements) from
    `sample_spacing(xyz, per_sample=True)`)."""
    n = probs.shape[1]
    sel, elem = elements
    own_sel = probs.argmax(-1).cpu().numpy()[sel]
    area_c = np.array([elem[own_sel == c].sum() for c in range(n)]) * area / max(elem.sum(), 1e-30)
    if cfg.image_size > 0:
        h = math.sqrt(area / (0.7 * cfg.image_size ** 2))
    elif pixel_size:
        h = pixel_size / max(cfg.texels_per_pixel, 1e-6)
    else:
        h = math.sqrt(area / (n * R * R * cfg.chart_fill))
    return h, area_c


def chart_scales(probs: torch.Tensor, uv: torch.Tensor, area_c: np.ndarray, h: float, k_area: float,
                 cfg: AtlasConfig) -> tuple[np.ndarray, np.ndarray]:
    """Texels per uv unit [n] that give every chart texel size h (world units) — measured per chart: its world
    area area_c [n] over the texels its samples cover — and each chart's occupancy radius in texels [n]."""
    from core.atlas.islands import UV_REACH, occupancy
    from core.atlas.texture import texel_spacing

    n = probs.shape[1]
    owner = probs.argmax(-1)
    uvn = uv.detach().cpu().numpy()
    s0 = 1.0 / (k_area * h)  # texels per uv unit where the distortion loss holds
    scale, fill = np.full(n, s0), np.ones(n)
    for c in range(n):
        m = (owner == c).cpu().numpy()
        if not m.any():
            continue
        lo, hi = UV_REACH  # the range the island grid keeps (build_islands)
        t = (np.clip(uvn[m, c], lo, hi) - lo) * s0
        cells = occupancy(t, int(math.ceil((hi - lo) * s0)) + 1, 1.0).sum()
        scale[c] = s0 * float(np.clip(math.sqrt(area_c[c] / (h * h) / max(cells, 1)), 0.25, 4.0))
        sp = texel_spacing(uv[torch.from_numpy(m).to(uv.device), c] * float(scale[c]))
        fill[c] = cfg.island_fill * max(1.0, sp)
    return scale, fill


def min_island_cells(h: float, cfg: AtlasConfig, pixel_size: float | None) -> int:
    """The texels of the smallest island kept at texel size h (world units): cfg.island_min_pixels training-pixel
    footprints, each (pixel_size / h)^2 texels (texels_per_pixel^2 where the footprint is unknown), at least 1."""
    per_pixel = pixel_size / h if pixel_size else cfg.texels_per_pixel
    return max(1, int(round(cfg.island_min_pixels * per_pixel * per_pixel)))


def island_layout(probs: torch.Tensor, uv: torch.Tensor, elements: tuple[np.ndarray, np.ndarray], area: float,
                  k_area: float, R: int, cfg: AtlasConfig, pixel_size: float | None) -> tuple[object, dict]:
    """Cut the charts to the surface they cover and pack them (core/atlas/islands.py) at one texel density for all
    charts. probs [S, n] and uv [S, n, 2] of the samples xyz [S, 3] (raw chart outputs); elements, area: from
    `sample_spacing(xyz, per_sample=True)` (the samples' area elements and their total); k_area: uv units per world
    unit the distortion loss aims at; R: the grid's chart side (sets the density when nothing else does).
    Texel size: pixel_size / texels_per_pixel when the images' footprint is known, else the grid's density; a fixed
    cfg.image_size, or a side above cfg.max_image_size, coarsens it until the islands fit.
    Returns (layout, info: texel size, per-chart scale, islands, seconds)."""
    from core.atlas.islands import build_islands

    t0 = time.perf_counter()
    h, area_c = _first_texel_size(probs, elements, area, R, cfg, pixel_size)
    info = {}
    for attempt in range(40):
        scale, fill = chart_scales(probs, uv, area_c, h, k_area, cfg)
        layout = build_islands(probs, uv, scale, cfg.island_pad, cfg.image_size, fill,
                               min_island_cells(h, cfg, pixel_size), transpose=cfg.island_transpose,
                               split=cfg.island_split, min_fill=cfg.island_min_fill, packer=cfg.island_packer,
                               pack_orders=cfg.island_pack_orders)
        if layout is not None and (cfg.image_size > 0 or layout.size <= cfg.max_image_size):
            info = {"texel_size": h, "chart_scale": scale.tolist(), "islands": layout.islands,
                    "atlas_size": layout.size, "island_seconds": time.perf_counter() - t0}
            return layout, info
        grow = 1.06 if layout is None else max(1.02, 1.01 * layout.size / cfg.max_image_size)
        h *= grow
    raise InputError(f"island layout: the charts do not fit a {cfg.image_size or cfg.max_image_size} texel atlas")


def _kmeans(x: torch.Tensor, k: int, iters: int = 15) -> torch.Tensor:
    """Deterministic k-means (farthest-point initialisation). x [S, 3] -> labels [S]."""
    centres = [x[0]]
    d = (x - x[0]).pow(2).sum(-1)
    for _ in range(k - 1):
        centres.append(x[d.argmax()])
        d = torch.minimum(d, (x - centres[-1]).pow(2).sum(-1))
    c = torch.stack(centres)
    for _ in range(iters):
        lab = torch.cdist(x, c).argmin(-1)
        for j in range(k):
            if (lab == j).any():
                c[j] = x[lab == j].mean(0)
    return torch.cdist(x, c).argmin(-1)


def flatness(xyz: torch.Tensor, k: int = 4, max_points: int = 20000) -> float:
    """Mean out-of-plane spread of k spatial clusters: sqrt(l3 / (l1 + l2)) of each cluster's covariance,
    weighted by cluster size. ~0 for pieces that are nearly planar, larger for curved or folded pieces."""
    x = xyz[torch.linspace(0, len(xyz) - 1, min(len(xyz), max_points)).long()].double()
    lab = _kmeans(x, k)
    total, acc = 0, 0.0
    for j in range(k):
        p = x[lab == j]
        if len(p) < 4:
            continue
        ev = torch.linalg.eigvalsh(torch.cov(p.T))  # ascending
        acc += len(p) * float(torch.sqrt(ev[0].clamp_min(0) / (ev[1] + ev[2]).clamp_min(1e-30)))
        total += len(p)
    return acc / max(total, 1)


def choose_chart_count(xyz: torch.Tensor, cfg: AtlasConfig) -> tuple[int, float]:
    """(n, flatness): the forced count, or 8 when 4 clusters are not flat enough (flatness > cfg.auto_flatness)."""
    f = flatness(xyz)
    forced = cfg.n_charts()
    return (forced if forced is not None else (8 if f > cfg.auto_flatness else 4)), f


def tangent_jacobian(J: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """The part of J [G, n, 2, 3] along the surfaces with unit normals [G, 3]: J (I - n n^T), so its singular values
    are those of the map restricted to the surface (a fold there: sigma2 -> 0). Zero or non-finite normals leave J
    as it is. Returns [G, n, 2, 3]."""
    nrm = normals.to(J.dtype)
    ok = torch.isfinite(nrm).all(-1, keepdim=True)
    nrm = torch.where(ok, nrm, torch.zeros_like(nrm))
    nrm = nrm * (nrm.norm(dim=-1, keepdim=True) > 0.5)  # a unit normal or none
    jn = (J * nrm[:, None, None, :]).sum(-1, keepdim=True)  # [G, n, 2, 1]
    return J - jn * nrm[:, None, None, :]


def _step_losses(atlas: Atlas, xb: torch.Tensor, rgb: torch.Tensor, cfg: AtlasConfig, jac_scale: float,
                 gen: torch.Generator, normals: torch.Tensor | None = None,
                 tangent: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """All loss terms on one batch. xb [B, 3] normalised points, rgb [B, 3], normals [B, 3] (w_normal > 0);
    tangent [B, 3]: the mid-surface's normals when the maps are fitted on it (the distortion then measures the
    map along the surface only), else None."""
    n, dev, B, U = atlas.n, xb.device, len(xb), cfg.uv_batch
    # Each network runs once on every row it needs (a row's output depends on that row alone): the samples' and the
    # random uv through the surface nets together, the samples and the generated points through the chart net
    # together, one Fourier encoding for the chart and texture-coordinate nets when they share its degree.
    shared = (type(atlas.chart) is ChartNet and type(atlas.tex) is TexCoordNet
              and atlas.chart.fourier == atlas.tex.fourier)
    enc = fourier_encode(xb, atlas.tex.fourier) if shared else None
    uv = atlas.tex(xb, enc)  # [B, n, 2]
    u = torch.rand(n, U, 2, generator=gen).to(dev)
    both = atlas.surf(torch.cat([uv.permute(1, 0, 2), u], dim=1))  # [n, B + U, 3]
    x_rec = both[:, :B].permute(1, 0, 2)  # [B, n, 3]
    flat = both[:, B:].reshape(-1, 3)  # [n U, 3]: s_c(u) of chart c in rows c U ... (c + 1) U - 1
    ar = torch.arange(n, device=dev)
    if shared:
        enc_s = fourier_encode(flat, atlas.tex.fourier)
        logits = atlas.chart(None, torch.cat([enc, enc_s]))  # [B + n U, n]
        u_rec = atlas.tex(None, enc_s)
    else:
        logits = atlas.chart(torch.cat([xb, flat]))
        u_rec = atlas.tex(flat)
    probs = torch.softmax(logits[:B], -1)  # [B, n]
    logits_s = logits[B:].view(n, U, n)
    u_rec = u_rec.view(n, U, n, 2)[ar, :, ar]  # [n, U, 2]
    pred = blend_charts(atlas.chart_textures, uv, probs)
    out = {
        "cycle3d": losses.cycle_3d(xb, x_rec, probs),
        "cycle2d": losses.cycle_2d(u, u_rec),
        "consistency": losses.chart_consistency(logits_s),
        "surface": losses.chamfer(xb, flat),
        "compact": losses.compactness(xb, probs),
        "range": losses.uv_range(uv),
        "texture": (pred - rgb).pow(2).mean(),
    }
    use_distortion = cfg.distortion and cfg.w_distortion > 0
    use_normal = cfg.w_normal > 0 and normals is not None
    use_fold = cfg.w_fold > 0 and tangent is not None
    if use_distortion or use_normal or use_fold:
        d = min(cfg.distortion_batch, len(xb))
        J, _ = uv_jacobian(atlas.tex, xb[:d])
        w = probs[:d] if cfg.distortion_weighting == "prob" else None
        if use_distortion:
            Jd = J if tangent is None else tangent_jacobian(J, tangent[:d])
            out["scaling"], out["area"] = distortion_terms(Jd * jac_scale, w)
        if use_normal:
            out["normal"] = losses.normal_flatness(J * jac_scale, normals[:d], probs[:d])
        if use_fold:
            out["fold"] = losses.fold_barrier(J, tangent[:d], probs[:d])
    return out


def _total(terms: dict[str, torch.Tensor], cfg: AtlasConfig) -> torch.Tensor:
    w = {"cycle3d": cfg.w_cycle3d, "cycle2d": cfg.w_cycle2d, "consistency": cfg.w_consistency,
         "surface": cfg.w_surface, "compact": cfg.w_compact, "range": cfg.w_range, "texture": cfg.w_texture,
         "scaling": cfg.w_distortion, "area": cfg.w_distortion, "normal": cfg.w_normal, "fold": cfg.w_fold}
    return sum(w[k] * v for k, v in terms.items())


@torch.no_grad()
def _predict(atlas: Atlas, xn: torch.Tensor, chunk: int = 32768) -> tuple[torch.Tensor, torch.Tensor]:
    """Chart probabilities [M, n] and uv [M, n, 2] for normalised points xn [M, 3]."""
    ps, uvs = [], []
    for s in range(0, len(xn), chunk):
        p, uv = atlas.outputs(xn[s:s + chunk])
        ps.append(p)
        uvs.append(uv)
    return torch.cat(ps), torch.cat(uvs)


def fit_atlas(xyz, rgb, cfg: AtlasConfig | None = None, progress: Optional[Callable[[float, str], None]] = None,
              quiet: bool = False, pixel_size: float | None = None) -> tuple[Atlas, dict]:
    """Learn an atlas from surface samples xyz [S, 3] and colours rgb [S, 3] in [0, 1] (see _fit_atlas), with
    torch limited to cfg.threads CPU threads for the duration (restored afterwards). pixel_size: world size of a
    training pixel on the surface (`pixel_footprint`), which sets the island atlas's resolution."""
    cfg = cfg or AtlasConfig()
    before = torch.get_num_threads()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    try:
        return _fit_atlas(xyz, rgb, cfg, progress, quiet, pixel_size)
    finally:
        torch.set_num_threads(before)


def _fit_atlas(xyz, rgb, cfg: AtlasConfig, progress: Optional[Callable[[float, str], None]] = None,
               quiet: bool = False, pixel_size: float | None = None) -> tuple[Atlas, dict]:
    """Learn an atlas from surface samples xyz [S, 3] and colours rgb [S, 3] in [0, 1].

    progress: optional callback(fraction, info) (e.g. Blender's UI); a text bar goes to stderr unless quiet.
    Returns (atlas, history) with history = {"n": charts, "flatness": f, "seconds": [...], "step": [...],
    "psnr": [...] (fitting PSNR on up to cfg.eval_samples samples), "phase": [...], "total_seconds": t}.
    """
    xyz = check_points(xyz, "surface samples xyz")
    rgb = torch.as_tensor(rgb).float()
    if rgb.shape != xyz.shape or not torch.isfinite(rgb).all():
        raise InputError(f"surface colours rgb: expected finite [S, 3] matching xyz {tuple(xyz.shape)}, "
                         f"got {tuple(rgb.shape)}")
    if len(xyz) < MIN_SAMPLES:
        raise InputError(f"surface samples: need at least {MIN_SAMPLES} samples, got {len(xyz)}")
    if cfg.texture_mode not in ("kernel", "descent"):
        raise InputError(f"AtlasConfig.texture_mode must be 'kernel' or 'descent', got {cfg.texture_mode!r}")
    rgb = rgb.clamp(0, 1)
    dev = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    t0 = time.perf_counter()

    n, flat = choose_chart_count(xyz, cfg)
    R = cfg.resolution(n)
    lo, hi = xyz.min(0).values, xyz.max(0).values
    centre, half = 0.5 * (lo + hi), float(0.5 * (hi - lo).max().clamp_min(1e-6))
    spacing, area, *elements = sample_spacing(xyz.numpy().astype(np.float64), per_sample=True)
    # UV scale: the distortion loss pulls sigma1*sigma2 to 1 in a frame where the whole surface covers
    # chart_fill of the n unit squares, i.e. world lengths times sqrt(n * fill / area).
    k_area = math.sqrt(n * cfg.chart_fill / max(area, 1e-12))
    jac_scale = 1.0 / (half * k_area)  # d(normalised x)/d(area frame): J_area = J_norm * jac_scale

    atlas = Atlas(n, R, cfg.pad, centre, half, cfg.width_chart, cfg.depth_chart, cfg.width_map, cfg.depth_map,
                  cfg.fourier_chart, cfg.fourier_map).to(dev)
    xn, rgb = atlas.normalise(xyz.to(dev)), rgb.to(dev)
    ev = torch.randperm(len(xn), generator=gen)[:cfg.eval_samples].to(dev)
    hist = {"n": n, "flatness": flat, "R": R, "steps": [], "seconds": [], "psnr": [], "phase": []}

    def log(step: int, phase: str) -> float:
        probs, uv = atlas.place(*_predict(atlas, xn[ev]))
        with torch.no_grad():
            p = psnr(blend_charts(atlas.chart_textures, uv, probs), rgb[ev])
        hist["steps"].append(step)
        hist["seconds"].append(time.perf_counter() - t0)
        hist["psnr"].append(p)
        hist["phase"].append(phase)
        return p

    tangent = None
    if cfg.mid_surface_maps and not cfg.mid_surface:
        raise InputError("AtlasConfig.mid_surface_maps needs mid_surface (--atlas-mid-surface)")
    if cfg.w_fold > 0 and not cfg.mid_surface_maps:
        raise InputError("AtlasConfig.w_fold needs mid_surface_maps (--atlas-mid-surface --atlas-mid-surface-maps)")
    if cfg.mid_surface_maps:  # the maps learn the surface the lookups will read (mid_surface below)
        xn = mid_surface(atlas, xyz, cfg, spacing, hist).to(dev)
        tangent = atlas.surface.orient().normals_at(atlas.denormalise(xn)).to(dev)  # one side per part
    normals = torch.from_numpy(sample_normals(xyz.numpy().astype(np.float64))).float().to(dev) \
        if cfg.w_normal > 0 else None
    nets = [p for name, p in atlas.named_parameters() if name != "textures"]
    opt = torch.optim.Adam([{"params": nets, "lr": cfg.lr}, {"params": [atlas.textures], "lr": cfg.texture_lr}],
                           fused=True)  # one fused kernel per step over all tensors (a third of foreach's time on CPU)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.1 ** (s / max(cfg.steps, 1)))
    total = cfg.steps + cfg.texture_steps
    bar = Progress(total, f"atlas ({n} charts)", callback=progress, enabled=not quiet)
    p = float("nan")
    for step in range(cfg.steps):
        idx = torch.randint(len(xn), (min(cfg.batch, len(xn)),), generator=gen).to(dev)
        terms = _step_losses(atlas, xn[idx], rgb[idx], cfg, jac_scale, gen,
                             None if normals is None else normals[idx], None if tangent is None else tangent[idx])
        opt.zero_grad(set_to_none=True)
        _total(terms, cfg).backward()
        opt.step()
        sched.step()
        if step % cfg.log_every == 0 or step == cfg.steps - 1:
            p = log(step + 1, "maps")
        bar.update(1, psnr=p)

    # Final texture with the maps frozen: chart probabilities and uv of every sample are fixed.
    if cfg.mid_surface and not cfg.mid_surface_maps:  # from here on every point reads the maps on the mid-surface
        xn = mid_surface(atlas, xyz, cfg, spacing, hist).to(dev)
    if cfg.layout == "islands" and cfg.island_sides:
        chart_sides(atlas, xyz, xn, cfg, spacing, hist)
    probs_all, uv_all = _predict(atlas, xn)
    if cfg.layout == "islands" and cfg.island_pieces:
        chart_pieces_step(atlas, xn, probs_all, uv_all, elements, area, k_area, R, cfg, pixel_size, spacing, hist)
        probs_all, uv_all = _predict(atlas, xn)
    if cfg.layout == "islands":
        layout, info = island_layout(probs_all, uv_all, elements, area, k_area, R, cfg, pixel_size)
        atlas.set_layout(layout)
        hist.update(info)
        R = layout.size
    probs_all, uv_all = atlas.place(probs_all, uv_all)
    if cfg.texture_mode == "kernel":
        # Kernel regression: each texel is the weighted mean colour of the samples around it (texture.py says why).
        with torch.no_grad():
            tex, _, hist["texture_sigma_texels"] = filled_kernel_texture(probs_all, uv_all, rgb, R,
                                                                         cfg.texture_sigma, labels=atlas.blur_labels)
            atlas.set_textures(tex)
        bar.update(cfg.texture_steps)
        p = log(cfg.steps + cfg.texture_steps, "texture")
    else:  # descent: Adam on the per-sample MSE, one bilinear lookup per chart and step
        topt = torch.optim.Adam([atlas.textures], lr=cfg.texture_lr, fused=True)  # (set_layout: new textures)
        for step in range(cfg.texture_steps):
            idx = torch.randint(len(xn), (min(8 * cfg.batch, len(xn)),), generator=gen).to(dev)
            pred = blend_charts(atlas.chart_textures, uv_all[idx], probs_all[idx])
            loss = (pred - rgb[idx]).pow(2).mean()
            topt.zero_grad(set_to_none=True)
            loss.backward()
            topt.step()
            if step % cfg.log_every == 0 or step == cfg.texture_steps - 1:
                p = log(cfg.steps + step + 1, "texture")
            bar.update(1, psnr=p)
        used = _used_texels(probs_all, uv_all, R)
        with torch.no_grad():
            atlas.set_textures(dilate_unused(atlas.chart_textures.clamp(0, 1), used))

    with torch.no_grad():
        atlas.canonicalise_textures()
        atlas.compute_texel_points(xyz, cfg.texel_max_dist * spacing, cfg.max_cycle(atlas.islands),
                                   "splat" if atlas.islands else cfg.texel_map, cfg.texture_sigma)
    if atlas.islands:
        hist["texel_stats"] = dict(atlas.texel_stats)
    p = log(total, "final")
    bar.close()
    hist["total_seconds"] = time.perf_counter() - t0
    hist["spacing"], hist["area"] = spacing, area
    return atlas, hist


def chart_sides(atlas: Atlas, xyz: torch.Tensor, xn: torch.Tensor, cfg: AtlasConfig, spacing: float,
                hist: dict) -> None:
    """Split the atlas's charts by side (core/atlas/sides.py): normals given one side from the mid-surface's anchor
    planes (the atlas's own when it has a mid-surface, else built from the samples xyz [S, 3] for the side rule
    only), each chart's majority orientation over the samples xn [S, 3] (network frame, as the lookups read them).
    hist gets "sides": seconds, reversed share of the samples, creases (|rho| < 0.2)."""
    from core.atlas.sides import ChartSides

    t0 = time.perf_counter()
    src = atlas.surface if atlas.surface is not None else SurfaceProjection.from_samples(
        xyz.numpy(), neighbours=cfg.island_sides_neighbours, max_ratio=cfg.mid_surface_max_ratio, seed=cfg.seed,
        max_anchors=cfg.island_sides_anchors)
    surf = SurfaceProjection(src.centres, src.normals, src.bandwidth, src.k).orient()  # a copy: projection untouched
    h = cfg.island_sides_step * spacing / atlas.half
    sides = ChartSides(surf, np.ones(atlas.n_net, np.float32), h, cfg.island_sides_crease)
    rhos, probs = [], []
    with torch.no_grad():
        for s in range(0, len(xn), 32768):
            x = xn[s:s + 32768]
            rhos.append(sides.rho(atlas.tex, x, atlas.denormalise(x)))
            probs.append(torch.softmax(atlas.chart(x), -1))
    rho, probs = torch.cat(rhos), torch.cat(probs)
    major = ChartSides.majority_of(rho, probs)
    chart = probs.argmax(-1)
    r = rho[torch.arange(len(rho)), chart] * torch.from_numpy(major)[chart]
    rev = r < -sides.crease
    for c in range(atlas.n_net):  # a chart with few samples on its reversed side stays whole (no seams for them)
        m = chart == c
        if not bool(m.any()) or float(rev[m].float().mean()) < cfg.island_sides_min_share:
            major[c] = 0.0
    sides.majority = torch.from_numpy(major)
    split = major[chart.numpy()] != 0
    hist["sides"] = {"seconds": round(time.perf_counter() - t0, 2), "split": int((major != 0).sum()),
                     "reversed": float((rev & torch.from_numpy(split)).float().mean()),
                     "crease": float((rho[torch.arange(len(rho)), chart].abs() < 0.2).float().mean())}
    atlas.sides = sides if bool((major != 0).any()) else None  # nothing split: the atlas of one side per chart


def chart_pieces_step(atlas: Atlas, xn: torch.Tensor, probs: torch.Tensor, uv: torch.Tensor,
                      elements: tuple[np.ndarray, np.ndarray], area: float, k_area: float, R: int, cfg: AtlasConfig,
                      pixel_size: float | None, spacing: float, hist: dict) -> None:
    """Cut every sub-chart where its map overlaps itself (core/atlas/pieces.py), from the samples xn [S, 3]
    (network frame, as lookups read them) with their sub-chart outputs probs [S, n_sub], uv [S, n_sub, 2]; texel
    coordinates at the density the island layout tries first (elements, area as `island_layout` takes them). Sets atlas.pieces (None when no sub-chart is cut);
    hist gets "pieces": seconds, layout charts, sub-charts cut."""
    from core.atlas.islands import UV_REACH
    from core.atlas.pieces import ChartPieces, chart_pieces

    t0 = time.perf_counter()
    h, area_c = _first_texel_size(probs, elements, area, R, cfg, pixel_size)
    scale, _ = chart_scales(probs, uv, area_c, h, k_area, cfg)
    world = atlas.denormalise(xn).cpu().numpy()
    sub = probs.argmax(-1).cpu().numpy()
    uvn = uv.detach().cpu().numpy()
    centres, subs, pieces, first, nxt = [], [], [], [], 0
    for s in range(probs.shape[1]):
        m = sub == s
        first.append(nxt)
        if m.sum() < 2 * cfg.island_pieces_min_samples:
            nxt += 1
            continue
        cen, lab = chart_pieces(world[m], np.clip(uvn[m, s], *UV_REACH) * scale[s], spacing, cfg.island_pieces_voxel,
                                cfg.island_pieces_far, cfg.island_pieces_texels, cfg.island_pieces_min_samples)
        k = int(lab.max()) + 1 if len(lab) else 1
        if k > 1:  # only cut sub-charts keep their patches (the others' points all read their one piece)
            centres.append(cen)
            subs.append(np.full(len(cen), s))
            pieces.append(nxt + lab)
        nxt += k
    cut = len(centres)
    atlas.pieces = None if not cut else ChartPieces(np.concatenate(centres), np.concatenate(subs),
                                                    np.concatenate(pieces), np.asarray(first))
    hist["pieces"] = {"seconds": round(time.perf_counter() - t0, 2), "charts": nxt, "cut": cut}


def mid_surface(atlas: Atlas, xyz: torch.Tensor, cfg: AtlasConfig, spacing: float, hist: dict) -> torch.Tensor:
    """Give the atlas its mid-surface projection (core/atlas/surface.py) built from the samples xyz [S, 3] and
    return the projected samples in the network frame [S, 3]; hist gets the median move in sample spacings."""
    t0 = time.perf_counter()
    atlas.surface = SurfaceProjection.from_samples(xyz.numpy(), neighbours=cfg.mid_surface_neighbours,
                                                   max_ratio=cfg.mid_surface_max_ratio, seed=cfg.seed,
                                                   adaptive=cfg.mid_surface_adaptive)
    moved = atlas.on_surface(xyz)
    planes = float((atlas.surface.normals != 0).any(1).mean()) if len(atlas.surface) else 0.0
    hist["mid_surface"] = {"anchors": len(atlas.surface), "planes": planes,
                           "seconds": round(time.perf_counter() - t0, 2),
                           "move_median": float((moved - xyz).norm(dim=-1).median()) / max(spacing, 1e-12)}
    return atlas.normalise(moved.to(atlas.device))


def _used_texels(probs: torch.Tensor, uv: torch.Tensor, R: int, min_prob: float = 1e-3) -> torch.Tensor:
    """Texels inside the bilinear footprint of some sample with P(c|x) > min_prob. probs [S, n], uv [S, n, 2]
    -> used [n, R, R] bool."""
    n = probs.shape[1]
    used = torch.zeros(n, R * R, dtype=torch.bool, device=probs.device)
    f = uv.clamp(0, 1) * R - 0.5  # continuous texel index of the sample
    base = f.floor().long()
    for dr in (0, 1):
        for dc in (0, 1):
            col = (base[..., 0] + dc).clamp(0, R - 1)
            row = (base[..., 1] + dr).clamp(0, R - 1)
            flat = row * R + col  # [S, n]
            for c in range(n):
                sel = probs[:, c] > min_prob
                used[c, flat[sel, c]] = True
    return used.view(n, R, R)


@torch.no_grad()
def quality_report(atlas: Atlas, xyz, rgb, area: float, chart_fill: float = 0.5, max_points: int = 4096) -> dict:
    """Measured atlas quality on samples xyz [S, 3] / rgb [S, 3]:
    PSNR of lookup, utilisation of the packed image, share of valid texels, and the median / 95th percentile of
    sigma1/sigma2 (anisotropy, 1 = conformal) and of sigma1*sigma2 in the area frame (1 = the intended texel
    density) for each sample's most probable chart."""
    from core.atlas.packing import utilisation

    xyz, rgb = check_points(xyz).to(atlas.device), torch.as_tensor(rgb).float().to(atlas.device)
    chart, pix = atlas.atlas_pixel_coords(xyz)
    sel = torch.linspace(0, len(xyz) - 1, min(len(xyz), max_points)).long().to(atlas.device)
    jac_scale = 1.0 / (atlas.half * math.sqrt(atlas.n * chart_fill / max(area, 1e-12)))
    with torch.enable_grad():
        J, _ = uv_jacobian(atlas.tex, atlas.normalise(xyz[sel]))
    from core.atlas.distortion import singular_values_2x3

    J = J.detach()[torch.arange(len(sel)), atlas.net_chart(chart[sel])] * jac_scale  # [P, 2, 3]
    s1, s2, log_area = singular_values_2x3(J)
    aniso = (s1 / s2.clamp_min(1e-12)).cpu().numpy()
    areas = torch.exp(log_area).cpu().numpy()
    tp = atlas.texel_points()
    L = atlas.layout
    interior = L.n * L.R * L.R
    return {
        "psnr": psnr(atlas.lookup(xyz), rgb),
        "utilisation": utilisation(pix.cpu().numpy(), L.shape),
        "utilisation_interior": utilisation(pix.cpu().numpy(), L.shape) * L.shape[0] * L.shape[1] / interior,
        "texel_valid": float(torch.isfinite(tp).all(-1).sum()) / interior,
        "aniso_median": float(np.median(aniso)), "aniso_p95": float(np.percentile(aniso, 95)),
        "area_median": float(np.median(areas)), "area_p95": float(np.percentile(areas, 95)),
        "area_p5": float(np.percentile(areas, 5)),
        "chart_share": torch.bincount(chart, minlength=atlas.n).float().div(len(chart)).tolist(),
    }


def fold_report(atlas: Atlas, xyz, max_points: int = 20000, seed: int = 0) -> dict:
    """How much the chart maps fold where the lookups read them, on samples xyz [S, 3] (at most max_points):
    each sample's chart map restricted to the surface (the mid-surface when the atlas has one), its orientation
    rho = det / (|du| |dv|) against the surface's normals given one side (`SurfaceProjection.orient`; without a
    mid-surface the planes are built from xyz for the measurement only). Returns {"reversed": share of the
    samples whose rho has the sign opposite to their chart's P-weighted majority — a chart laying two parts of the
    surface over each other, "crease": share with |rho| < 0.2, "charts": per chart [reversed share, samples]}."""
    x = check_points(xyz, "samples")
    g = torch.Generator().manual_seed(seed)
    x = x[torch.randperm(len(x), generator=g)[:max_points]].to(atlas.device)
    surf = atlas.surface if atlas.surface is not None else SurfaceProjection.from_samples(x.cpu().numpy())
    surf = SurfaceProjection(surf.centres, surf.normals, surf.bandwidth, surf.k).orient()  # a copy: atlas untouched
    pts = atlas.on_surface(x)
    nrm = surf.normals_at(pts).to(atlas.device).double()
    probs, _ = atlas.chart_uv(x)
    chart = atlas.net_chart(probs.argmax(-1))  # the chart network (a split atlas: both sides of it together)
    with torch.enable_grad():
        J, _ = uv_jacobian(atlas.tex, atlas.normalise(pts))
    J = J.detach()[torch.arange(len(x), device=atlas.device), chart].double()
    du, dv = J[:, 0], J[:, 1]
    rho = (torch.linalg.cross(du, dv) * nrm).sum(-1) / (du.norm(dim=-1) * dv.norm(dim=-1)).clamp_min(1e-300)
    ok = (nrm.norm(dim=-1) > 0.5) & torch.isfinite(rho)
    rev = torch.zeros(len(x), dtype=torch.bool, device=atlas.device)
    per = []
    for c in range(atlas.n_net):
        m = (chart == c) & ok
        if bool(m.any()):
            rev[m] = (rho[m] < 0) if float(rho[m].sum()) >= 0 else (rho[m] > 0)
        per.append([float(rev[m].float().mean()) if bool(m.any()) else 0.0, int(m.sum())])
    n_ok = max(int(ok.sum()), 1)
    return {"reversed": float(rev[ok].sum()) / n_ok, "crease": float((rho[ok].abs() < 0.2).sum()) / n_ok,
            "charts": per}
