"""The Atlas: learned charts + texture maps + packed image + texel->surface map, and its plain-array form
for the .pgt file (no pickle: only named float32 arrays and a JSON-able meta dict)."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn

from core.atlas.config import MAX_CHART_RES, WORLD_SCALES
from core.atlas.islands import IslandLayout
from core.atlas.networks import ChartNet, SurfaceNet, TexCoordNet, fourier_encode
from core.atlas.pieces import ChartPieces
from core.atlas.packing import GridLayout, blend_charts, chart_coords, pack, texel_uv, unpack, uv_to_pixel
from core.atlas.sides import ChartSides
from core.atlas.surface import SurfaceProjection
from core.atlas.texture import kernel_texture, local_linear_points
from core.util.errors import InputError, ModelFileError

# 1: grid layout; 2: island layout ("layout": "islands"); 3: islands some of which are transposed
# (atlas/islands/orient, which a version-2 reader would ignore and misplace); 4: lookups projected onto the samples'
# mid-surface first (atlas/surface/..., which an older reader would ignore and read other texels); 5: island charts
# split by side (atlas/sides/..., 2n sub-charts over n chart networks); 6: sub-charts cut into pieces where their
# map overlaps itself (atlas/pieces/..., more layout charts than sub-charts); 7: an island layout's cell grids stored
# cropped to each chart's occupied cells (atlas/islands/cell_boxes, cell_crops, grid instead of the whole
# atlas/islands/cells, which an older reader would miss). Files are written at the lowest version that describes
# them, so older readers load every file they can read correctly: every island atlas is version 7.
FORMAT_VERSION = 7
READ_VERSIONS = (1, 2, 3, 4, 5, 6, 7)
_CHUNK = 65536
MAX_BAKE_SAMPLES = 200_000  # stored surface samples for baking (2.4 MB); more are subsampled


def check_points(x, name: str = "points") -> torch.Tensor:
    """Validate a point array [M, 3] of finite numbers and return it as a float32 tensor."""
    x = torch.as_tensor(x)
    if x.dim() != 2 or x.shape[1] != 3:
        raise InputError(f"{name}: expected shape [M, 3], got {tuple(x.shape)}")
    x = x.float()
    if not torch.isfinite(x).all():
        raise InputError(f"{name}: contains NaN or infinite values")
    return x


MAX_CHARTS = 64


class Atlas(nn.Module):
    """n charts with R x R texels each; points are normalised as (x - centre) / half before the networks.
    Built on a grid layout (n squares, used while fitting); `set_layout` switches to an island layout
    (core/atlas/islands.py), where every point has one chart and chart coordinates are placed in the packed image.

    Shapes: chart_uv(x [M, 3]) -> (probs [M, n], uv [M, n, 2]); lookup(x [M, 3], image [H, W, 3] | None) -> [M, 3];
    atlas_pixel_coords(x [M, 3]) -> (chart [M] long, pixel [M, 2] (col, row)); packed_image() -> [H, W, 3];
    texel_points() -> [H, W, 3] (NaN where no surface).
    """

    def __init__(self, n: int, R: int, pad: int, centre, half: float, width_chart: int = 64, depth_chart: int = 3,
                 width_map: int = 128, depth_map: int = 4, fourier_chart: int = 1, fourier_map: int = 4):
        super().__init__()
        if not (1 <= n <= MAX_CHARTS and 2 <= R <= MAX_CHART_RES and 0 <= pad <= 64
                and WORLD_SCALES[0] <= half <= WORLD_SCALES[1]):
            raise InputError(f"atlas: invalid sizes n={n} R={R} pad={pad} half={half} (limits: 1-{MAX_CHARTS} charts "
                             f"of 2-{MAX_CHART_RES} texels, pad 0-64, the scene's half-size {WORLD_SCALES[0]:g}-"
                             f"{WORLD_SCALES[1]:g})")
        for key, val, lo, hi in (("width_chart", width_chart, 1, 4096), ("width_map", width_map, 1, 4096),
                                 ("depth_chart", depth_chart, 0, 16), ("depth_map", depth_map, 0, 16),
                                 ("fourier_chart", fourier_chart, 0, 16), ("fourier_map", fourier_map, 0, 16)):
            if not lo <= val <= hi:  # checked before the networks are allocated
                raise InputError(f"atlas: {key} must lie in [{lo}, {hi}], got {val}")
        self.layout = GridLayout(n, R, pad)
        self.arch = dict(width_chart=width_chart, depth_chart=depth_chart, width_map=width_map, depth_map=depth_map,
                         fourier_chart=fourier_chart, fourier_map=fourier_map)
        self.half = float(half)
        self.register_buffer("centre", torch.as_tensor(centre, dtype=torch.float32).reshape(3).clone())
        self.chart = ChartNet(n, width_chart, depth_chart, fourier_chart)
        self.tex = TexCoordNet(n, width_map, depth_map, fourier_map)
        self.surf = SurfaceNet(n, width_map, depth_map, fourier_map)
        self.textures = nn.Parameter(torch.full((n, 3, R, R), 0.5))
        self.register_buffer("texel_xyz", torch.full((*self.layout.shape, 3), float("nan")))
        # Surface samples [S, 3] the texel map was built from, kept for baking (core/edits/bake.py), and the
        # kernel width they were splatted with; None in files written before they were stored.
        self.bake_samples: torch.Tensor | None = None
        self.bake_sigma = 1.0
        # Mid-surface projection applied to every point before the chart networks (core/atlas/surface.py); None:
        # points go to the networks as they are (files written before it existed, AtlasConfig.mid_surface off).
        self.surface: SurfaceProjection | None = None
        # Island charts split by side (core/atlas/sides.py): the layout then has 2 n_net sub-charts, 2c and 2c + 1
        # both read through chart network c. None: one layout chart per network chart.
        self.sides: ChartSides | None = None
        # Sub-charts cut into pieces where their map overlaps itself (core/atlas/pieces.py): each piece is a layout
        # chart. None: one layout chart per sub-chart.
        self.pieces: ChartPieces | None = None
        self.n_net = n

    @property
    def n(self) -> int:
        """Charts of the layout (what chart_uv, the textures and the packed image index); 2 n_net when split by
        side."""
        return self.layout.n

    @property
    def n_sub(self) -> int:
        """Sub-charts: the chart networks' charts, two per chart when split by side."""
        return self.n_net * (2 if self.sides is not None else 1)

    def net_chart(self, chart: torch.Tensor) -> torch.Tensor:
        """Layout chart indices [M] -> the chart network each reads through [M]."""
        if self.pieces is not None:
            chart = self.pieces.sub_of.to(chart.device)[chart]
        return chart // 2 if self.sides is not None else chart

    def _sub_has_islands(self) -> torch.Tensor:
        """[n_sub] bool: the sub-chart has islands (any of its pieces)."""
        has = self.layout.has_islands
        if self.pieces is None:
            return has
        return torch.zeros(self.n_sub, dtype=torch.long).index_add_(0, self.pieces.sub_of, has.long()) > 0

    def outputs(self, xn: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw chart outputs at network-frame points xn [M, 3] (already on the mid-surface when there is one):
        (probs [M, n] softmax, uv [M, n, 2] t_c) over the layout's charts — split by side when `sides` is set
        (a sub-chart without islands hands its points to the other side of its chart)."""
        if (type(self.chart) is ChartNet and type(self.tex) is TexCoordNet
                and self.chart.fourier == self.tex.fourier):  # one Fourier encoding serves both networks
            enc = fourier_encode(xn, self.tex.fourier)
            p, uv = torch.softmax(self.chart(xn, enc), dim=-1), self.tex(xn, enc)
        else:
            p, uv = torch.softmax(self.chart(xn), dim=-1), self.tex(xn)
        sub_has = self._sub_has_islands() if self.islands else None  # [n_sub]; None before there is a layout
        if self.sides is not None:
            rev = self.sides.reversed(self.tex, xn, self.denormalise(xn), uv)  # t_c at xn: the uv above
            if sub_has is not None:
                has = sub_has.to(rev.device).view(-1, 2)                       # [n_net, 2] (majority, reversed)
                rev = torch.where(has[:, 1], rev, torch.zeros_like(rev))
                rev = torch.where(has[:, 0], rev, torch.ones_like(rev) & has[:, 1])
            p, uv = ChartSides.expand(p, uv, rev)
        if self.pieces is not None:
            p, uv = self.pieces.expand(p, uv, self.denormalise(xn), sub_has,
                                       self.layout.has_islands if self.islands else None)
        return p, uv

    @property
    def islands(self) -> bool:
        return getattr(self.layout, "kind", "grid") == "islands"

    @property
    def blur_labels(self) -> torch.Tensor | None:
        """[R, R] island id of each pixel for texture kernels (island layout), None for the grid."""
        return self.layout.label.to(self.device) if self.islands else None

    def set_layout(self, layout: IslandLayout) -> None:
        """Switch to an island layout: a new texture (0.5) and an empty texel map. An island layout's charts all
        read one image, so `textures` is that image alone, [1, 3, size, size] (`chart_textures`: the n views)."""
        want = self.pieces.n if self.pieces is not None else self.n_sub
        if layout.n != want:
            raise InputError(f"island layout has {layout.n} charts, the atlas {want}")
        self.layout = layout
        self.textures = nn.Parameter(torch.full((1, 3, layout.size, layout.size), 0.5, device=self.device))
        self.texel_xyz = torch.full((*layout.shape, 3), float("nan"), device=self.device)

    @property
    def chart_textures(self) -> torch.Tensor:
        """Every chart's texture [n, 3, R, R]: the grid's n squares, or n views (no copy) of an island layout's one
        image."""
        return self.textures.expand(self.n, -1, -1, -1) if self.islands else self.textures

    @torch.no_grad()
    def set_textures(self, textures: torch.Tensor) -> None:
        """Set the chart textures from [n, 3, R, R]; an island layout keeps each pixel from the chart that owns it
        (its packed image)."""
        if self.islands:
            textures = self.layout.unpack(self.layout.pack(textures))[:1]
        self.textures.copy_(textures)

    @torch.no_grad()
    def canonicalise_textures(self) -> None:
        """Island layout: make the texture the packed image a saved file holds (pixels beyond every island's
        padding: the nearest padding pixel's colour), so lookups before and after saving agree bit for bit. No-op
        for the grid layout."""
        if self.islands:
            self.set_textures(self.chart_textures.detach())

    def place(self, probs: torch.Tensor, uv: torch.Tensor,
              own_chart_only: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw chart outputs (probs [M, n], t_c(x) [M, n, 2]) -> what lookups use: unchanged for the grid layout;
        for islands one chart per point (one-hot probs) and coordinates in the packed image (pixel = uv * R).
        own_chart_only (islands): only each point's own chart is placed and its coordinates stand in every chart's
        slot — what a lookup blended by the one-hot probs reads, at 1/n of the cost."""
        if not self.islands:
            return probs, uv
        hard = self.layout.hard_probs(probs)
        if not own_chart_only:
            return hard, self.layout.place(uv)
        chart = hard.argmax(-1)
        own = self.layout.place_one(chart_coords(uv, chart), chart)
        return hard, own[:, None].expand(-1, uv.shape[1], 2)

    @property
    def device(self) -> torch.device:
        return self.centre.device

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """World points [M, 3] -> network frame [M, 3]."""
        return (x - self.centre) / self.half

    def denormalise(self, xn: torch.Tensor) -> torch.Tensor:
        return xn * self.half + self.centre

    def on_surface(self, x: torch.Tensor) -> torch.Tensor:
        """World points [M, 3] -> the points the chart networks see [M, 3]: projected onto the samples'
        mid-surface when the atlas has one (`surface`), else unchanged."""
        return x if self.surface is None else self.surface.project(x)

    # --- queries (no gradients, chunked) -------------------------------------------------------------
    @torch.no_grad()
    def chart_uv(self, x, placed: bool = True, own_chart_only: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """x [M, 3] world -> (probs [M, n] chart probabilities, uv [M, n, 2] per-chart texture coordinates), at
        x projected onto the samples' mid-surface when the atlas has one (`on_surface`).
        Island layout: probs one-hot (one chart per point), uv already placed in the packed image (see place;
        own_chart_only: each point's own chart's coordinates in every slot, for callers that read only those);
        placed False: the networks' raw outputs (softmax, t_c), to interpolate before `place`."""
        x = check_points(x).to(self.device)
        ps, uvs = [], []
        for s in range(0, len(x), _CHUNK):
            xn = self.normalise(self.on_surface(x[s:s + _CHUNK]))
            p, uv = self.outputs(xn)
            if placed:
                p, uv = self.place(p, uv, own_chart_only=own_chart_only)
            ps.append(p)
            uvs.append(uv)
        if not ps:
            return torch.zeros(0, self.n, device=self.device), torch.zeros(0, self.n, 2, device=self.device)
        return torch.cat(ps), torch.cat(uvs)

    @torch.no_grad()
    def lookup(self, x, image=None) -> torch.Tensor:
        """Colour at surface points x [M, 3]: sum_c P(c|x) bilinear(T_c, t_c(x)) -> rgb [M, 3].

        image: an (edited) packed atlas [H, W, 3] (numpy or torch); None = the fitted one.
        """
        tex = self.chart_textures if image is None else unpack(torch.as_tensor(image).float().to(self.device), self.layout)
        probs, uv = self.chart_uv(x)
        return blend_charts(tex, uv, probs)

    @torch.no_grad()
    def atlas_pixel_coords(self, x) -> tuple[torch.Tensor, torch.Tensor]:
        """Where x [M, 3] lands in the packed image, in its most probable chart:
        (chart [M] long, pixel [M, 2] as continuous (col, row); pixel (r, c) is centred at (c + 0.5, r + 0.5))."""
        probs, uv = self.chart_uv(x)
        chart = probs.argmax(-1)
        uv_best = chart_coords(uv, chart)
        return chart, uv_to_pixel(uv_best, chart, self.layout)

    @torch.no_grad()
    def packed_image(self) -> torch.Tensor:
        """The fitted atlas as one image [H, W, 3] float32 in [0, 1], row 0 = top."""
        return pack(self.chart_textures.detach().clamp(0, 1), self.layout)

    def texel_points(self) -> torch.Tensor:
        """Canonical 3-D point of every packed-image pixel [H, W, 3]; NaN where no surface (padding, unused)."""
        return self.texel_xyz

    @torch.no_grad()
    def compute_texel_points(self, samples, max_dist: float, max_cycle: float = 2.0, mode: str = "splat",
                             sigma: float = 1.0) -> torch.Tensor:
        """Fill the texel map: the canonical 3-D point of every packed-image pixel. samples [S, 3] world (the
        stage-2 surface samples); max_dist in world units; max_cycle in texels. Returns [H, W, 3].

        mode "splat" (default): each texel's point is the kernel-weighted mean position of the samples that t_c
        maps around it (the same kernel as the texture, width sigma sample spacings), so the map is consistent with
        lookups by construction. "inverse": s_c at texel centres — the surface-coordinate net misses its own
        texel by several texels (median) on real samples, which shifts anything baked through it (docs/atlas.md).
        A texel keeps its point only where the chart net picks chart c there, the point lies within max_dist of
        some sample, and t_c(point) returns to within max_cycle texels of the texel centre.
        The samples (at most MAX_BAKE_SAMPLES) and sigma are kept as `bake_samples` / `bake_sigma` for baking.
        With a mid-surface (`surface`) the samples are projected onto it first, for the map and the bake alike.
        """
        if mode not in ("splat", "inverse"):
            raise InputError(f"texel map mode must be 'splat' or 'inverse', got {mode!r}")
        L, R = self.layout, self.layout.R
        samples = self.on_surface(check_points(samples, "surface samples").to(self.device))
        if self.islands:
            if mode != "splat":
                raise InputError("the island layout builds its texel map from the forward map only (texel_map splat)")
            out = self._island_texel_points(samples, max_dist, max_cycle, sigma)
            self._keep_bake_samples(samples, sigma)
            return out
        u = texel_uv(R, self.device)  # [R*R, 2]
        if mode == "splat":
            probs, uv = self.chart_uv(samples)
            mean, covered, _ = kernel_texture(probs, uv, samples, R, sigma)  # [n, 3, R, R], [n, R, R]
            cand = mean.permute(0, 2, 3, 1).reshape(self.n, R * R, 3)
            cand = torch.where(covered.reshape(self.n, R * R, 1), cand, torch.full_like(cand, float("nan")))
        else:
            with torch.no_grad():
                cand = self.denormalise(self.surf(u[None].expand(self.n, -1, -1).contiguous()))  # [n, R*R, 3]
        out = torch.full((*L.shape, 3), float("nan"), device=self.device)
        tree = cKDTree(samples.cpu().numpy())
        for c in range(self.n):
            xw = cand[c]
            have = torch.isfinite(xw).all(-1)
            keep = torch.zeros_like(have)
            if have.any():
                probs, uv = self.chart_uv(xw[have])
                pick = probs.argmax(-1) == c
                cyc = (uv[:, c] - u[have]).norm(dim=-1) * R <= max_cycle
                dist, _ = tree.query(xw[have].cpu().numpy(), k=1)
                near = torch.from_numpy(dist <= max_dist).to(self.device)
                keep[have] = pick & cyc & near
            pts = torch.where(keep[:, None], xw, torch.full_like(xw, float("nan")))
            r0, c0 = L.origin(c)
            out[r0:r0 + R, c0:c0 + R] = pts.reshape(R, R, 3)
        self.texel_xyz.copy_(out)
        self._keep_bake_samples(samples, sigma)
        return out

    def _keep_bake_samples(self, samples: torch.Tensor, sigma: float) -> None:
        keep = samples if samples.shape[0] <= MAX_BAKE_SAMPLES else samples[
            torch.randperm(samples.shape[0], generator=torch.Generator().manual_seed(0))[:MAX_BAKE_SAMPLES].to(
                samples.device)]
        self.bake_samples, self.bake_sigma = keep.detach().float().cpu().clone(), float(sigma)

    @torch.no_grad()
    def _newton_to_texels(self, x: torch.Tensor, slope: torch.Tensor, chart: torch.Tensor, target: torch.Tensor,
                          iters: int = 6, max_move: float = 8.0, chunk: int = 32768, h: float = 0.25,
                          orient: torch.Tensor | None = None, tol: float = 0.01) -> torch.Tensor:
        """Move points x [K, 3] within their surface's tangent plane (slope [K, 2, 3]: dx per texel) until their
        chart's forward map (chart [K]) sends them to target [K, 2] pixel (col, row): Gauss-Newton on
        q -> pixel(x + q slope) with derivatives by finite differences of h texels along the slope, at most
        max_move of the point's own texel sizes (its slope's longer side) from the local-linear point (and kept only
        if it still lies near a sample).
        orient [K, 2, 2]: the target island's orientation (chart texel offsets -> image offsets; None: identity).
        Ill-conditioned steps are skipped; a point stops once it lands within tol texels of its target."""
        L, A = self.layout, self.layout.size
        aff = L.affine.to(self.device)
        out = x.clone()
        if len(x) == 0:
            return out
        # max_move of each point's own texel sizes: where the map squeezes the surface (an anisotropic texel many
        # sample spacings long) the local-linear point can lie that far from the texel's preimage
        reach_all = (max_move * slope.norm(dim=-1).amax(-1)).nan_to_num(0.0).clamp_min(1e-12)  # [K]

        def to_texels(raw, ch):  # raw t_c [K, 2] -> chart texel coordinates (before the island offset) [K, 2]
            return (aff[ch, :, :2] @ raw[..., None])[..., 0] + aff[ch, :, 2]

        def chart_texels(pts, ch, net, ar):
            return to_texels(self.tex(self.normalise(self.on_surface(pts)))[ar, net], ch)

        for s in range(0, len(x), chunk):
            x0, B, ch, tg = x[s:s + chunk], slope[s:s + chunk], chart[s:s + chunk], target[s:s + chunk]
            reach = reach_all[s:s + chunk, None]
            rot = None if orient is None else orient[s:s + chunk].to(x0.dtype)
            net = self.net_chart(ch)
            q = torch.zeros(len(x0), 2, device=self.device)
            xs = x0.clone()
            best, best_miss = x0.clone(), torch.full((len(x0),), float("inf"), device=self.device)
            act = torch.arange(len(x0), device=self.device)  # points still iterating
            for it in range(iters + 1):
                ar = torch.arange(len(act), device=self.device)
                raw = self.tex(self.normalise(self.on_surface(xs[act])))[ar, net[act]]
                pix = self.layout.place_one(raw, ch[act]) * A
                r = pix - tg[act]
                # keep the iterate that lands nearest its texel: where the map is not smooth enough for
                # Gauss-Newton (a fold, the mid-surface's anchor planes changing) a step can land farther away
                miss = r.norm(dim=-1).nan_to_num(float("inf"))
                better = miss < best_miss[act]
                best[act[better]], best_miss[act[better]] = xs[act[better]], miss[better]
                go = miss > tol  # points within tol of their texel stop here
                if it == iters or not bool(go.any()):
                    break
                act, raw, r, ar = act[go], raw[go], r[go], ar[:int(go.sum())]
                if rot is not None:  # the miss in chart texels: image offsets turned back (orthogonal matrices)
                    r = (rot[act].transpose(1, 2) @ r[..., None])[..., 0]
                cha, neta, xa, Ba = ch[act], net[act], xs[act], B[act]
                t0 = to_texels(raw, cha)  # the map at xs, evaluated above
                Mq = torch.stack([(chart_texels(xa + h * Ba[:, k], cha, neta, ar) - t0) / h for k in range(2)], -1)
                det = torch.linalg.det(Mq)
                ok = (det.abs() > 0.05) & torch.isfinite(det) & torch.isfinite(r).all(-1)
                dq = torch.zeros_like(r)
                dq[ok] = -torch.linalg.solve(Mq[ok], r[ok][..., None])[..., 0]
                qa = q[act] + dq
                d = (qa[:, :, None] * Ba).sum(1)
                qa = qa * (reach[act] / d.norm(dim=-1, keepdim=True).clamp_min(reach[act]))  # stay near the samples
                q[act] = qa
                xs[act] = x0[act] + (qa[:, :, None] * Ba).sum(1)
            out[s:s + chunk] = best
        return out

    @torch.no_grad()
    def _island_texel_points(self, samples: torch.Tensor, max_dist: float, max_cycle: float,
                             sigma: float) -> torch.Tensor:
        """Texel map of an island layout: every island pixel gets the kernel mean position of the samples that its
        owning chart maps around it; kept where that point's own chart is the owner, it lies within max_dist of
        a sample, and it maps back within max_cycle texels; island pixels left without a point take the sample
        that lands nearest them when it lands within max_cycle texels and max_dist of their local-linear point.
        Sets `texel_stats` (round trip of all candidates before that fallback, `nearest_sample`: texels it
        filled)."""
        L, A = self.layout, self.layout.size
        probs, uv = self.chart_uv(samples, own_chart_only=True)  # only each point's own chart is read below
        chart = probs.argmax(-1)
        owner = L.owner.to(self.device)
        cand = torch.full((A, A, 3), float("nan"), device=self.device)
        slope = torch.zeros(A, A, 2, 3, device=self.device)
        cov = torch.zeros(A, A, dtype=torch.bool, device=self.device)
        for c in range(self.n):  # one chart per point: each chart's samples give its own pixels' points
            sel = chart == c
            if not bool(sel.any()):
                continue
            pts_c, cov_c, slope_c = local_linear_points(uv[sel, c] * A, samples[sel], A, sigma,
                                                        labels=self.blur_labels, with_slope=True)
            mine = (owner == c) & cov_c
            cand[mine], slope[mine], cov[mine] = pts_c[mine], slope_c[mine], True
        cov &= L.island_pixels.to(self.device) & torch.isfinite(cand).all(-1)
        rows, cols = torch.nonzero(cov, as_tuple=True)
        pts = self._newton_to_texels(cand[rows, cols], slope[rows, cols], owner[rows, cols],
                                     torch.stack([cols + 0.5, rows + 0.5], -1).float(),
                                     orient=L.orient_of_pixels(rows, cols).to(self.device))
        keep = torch.zeros(len(rows), dtype=torch.bool, device=self.device)
        miss = torch.full((len(rows),), float("inf"), device=self.device)
        if len(rows):
            p2, uv2 = self.chart_uv(pts, own_chart_only=True)
            c2 = p2.argmax(-1)
            pix = chart_coords(uv2, c2) * A
            centre = torch.stack([cols + 0.5, rows + 0.5], -1).to(pix.dtype)
            miss = torch.where(c2 == owner[rows, cols], (pix - centre).norm(dim=-1), miss)
            dist, _ = cKDTree(samples.cpu().numpy()).query(pts.cpu().numpy(), k=1)
            keep = (miss <= max_cycle) & torch.from_numpy(dist <= max_dist).to(self.device)
        out = torch.full((A, A, 3), float("nan"), device=self.device)
        out[rows[keep], cols[keep]] = pts[keep]
        # Island texels still without a point (Gauss-Newton did not converge): the sample that lands nearest the
        # texel centre, when it lands within max_cycle texels, in the texel's own chart (a surface point that maps
        # back within max_cycle by construction), and lies within max_dist of the texel's local-linear point (at a
        # fold the kernel mixes both layers and that point lies between them: such texels keep no point).
        rest_r, rest_c = torch.nonzero(L.island_pixels.to(self.device) & ~torch.isfinite(out).all(-1), as_tuple=True)
        nearest = 0
        if len(rest_r):
            spix = chart_coords(uv, chart) * A  # [S, 2] (col, row)
            d, j = cKDTree(spix.cpu().numpy()).query(torch.stack([rest_c + 0.5, rest_r + 0.5], -1).cpu().numpy(),
                                                     k=1, distance_upper_bound=max_cycle)
            hit = np.isfinite(d) & (d <= max_cycle)
            j = torch.from_numpy(np.where(hit, j, 0)).to(self.device)
            near = (samples[j] - cand[rest_r, rest_c]).norm(dim=-1) <= max_dist  # NaN (no kernel) -> False
            hit = torch.from_numpy(hit).to(self.device) & (chart[j] == owner[rest_r, rest_c]) & near
            out[rest_r[hit], rest_c[hit]] = samples[j[hit]]
            nearest = int(hit.sum())
        self.texel_xyz.copy_(out)
        n_isl = int(L.island_pixels.sum())
        self.texel_stats = {"island_texels": n_isl, "candidates": int(len(rows)), "kept": int(keep.sum()) + nearest,
                            "nearest_sample": nearest,
                            "round_trip_1": float((miss <= 1.0).float().mean()) if len(rows) else float("nan"),
                            "round_trip_1_of_island": float((miss <= 1.0).sum()) / max(n_isl, 1)}
        return out

    # --- serialisation ------------------------------------------------------------------------------
    def meta(self) -> dict:
        """JSON-able description needed to rebuild the atlas from its arrays."""
        L = self.layout
        # an island layout stores its cell grids cropped (IslandLayout.to_arrays): version 7 whatever it holds
        version, extra = (7 if self.islands else 1), {}
        if self.surface is not None:
            version, extra = max(version, 4), {"surface": self.surface.meta()}
        if self.sides is not None:
            extra = dict(extra, sides=self.sides.meta())
        if self.pieces is not None:
            extra = dict(extra, pieces={"n": self.pieces.n})
        return dict(version=version, n=self.n_net, R=L.R, pad=L.pad, half=self.half,
                    height=L.shape[0], width=L.shape[1], layout=getattr(L, "kind", "grid"),
                    uv_convention="u->col, v->row, row 0 = top", bake_sigma=self.bake_sigma, **self.arch, **extra)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """All state as named arrays (float32; the islands' and pieces' indices int32): 'atlas/image' [H, W, 3],
        'atlas/texel_points' [H, W, 3], 'atlas/centre' [3], the network weights under 'atlas/net/...' and, when
        known, 'atlas/bake_samples' [S, 3]."""
        arrays = {"atlas/image": pack(self.chart_textures.detach(), self.layout).cpu().numpy().astype(np.float32),
                  "atlas/texel_points": self.texel_xyz.cpu().numpy().astype(np.float32),
                  "atlas/centre": self.centre.cpu().numpy().astype(np.float32)}
        for name, p in self.named_parameters():
            if name != "textures":
                arrays[f"atlas/net/{name}"] = p.detach().cpu().numpy().astype(np.float32)
        if self.islands:
            arrays.update(self.layout.to_arrays())
        if self.bake_samples is not None:
            arrays["atlas/bake_samples"] = self.bake_samples.cpu().numpy().astype(np.float32)
        if self.surface is not None:
            arrays.update(self.surface.to_arrays())
        if self.sides is not None:
            arrays.update(self.sides.to_arrays())
        if self.pieces is not None:
            arrays.update(self.pieces.to_arrays())
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict, meta: dict, device="cpu") -> "Atlas":
        """Rebuild from `to_arrays()` / `meta()` output; missing or mis-shaped arrays raise ModelFileError."""
        try:
            if int(meta.get("version", -1)) not in READ_VERSIONS:
                raise ModelFileError(f"atlas: unsupported format version {meta.get('version')!r} "
                                     f"(this build reads versions {', '.join(map(str, READ_VERSIONS))})")
            kind = meta.get("layout", "grid")
            if kind not in ("grid", "islands"):
                raise ModelFileError(f"atlas: unknown layout {kind!r} (grid or islands)")
            keys = ("width_chart", "depth_chart", "width_map", "depth_map", "fourier_chart", "fourier_map")
            atlas = cls(int(meta["n"]), 2 if kind == "islands" else int(meta["R"]), int(meta["pad"]),
                        arrays["atlas/centre"], float(meta["half"]), **{k: int(meta[k]) for k in keys})
            if "sides" in meta:
                atlas.sides = ChartSides.from_arrays(arrays, meta["sides"])
                if atlas.sides.n != atlas.n_net:
                    raise ModelFileError(f"atlas: 'atlas/sides/majority' has {atlas.sides.n} entries for "
                                         f"{atlas.n_net} charts")
                if kind != "islands":
                    raise ModelFileError("atlas: charts split by side need the island layout")
            if "pieces" in meta:
                if kind != "islands":
                    raise ModelFileError("atlas: charts cut into pieces need the island layout")
                for key in ("centres", "sub", "piece", "first"):
                    if f"atlas/pieces/{key}" not in arrays:
                        raise ModelFileError(f"atlas: missing array 'atlas/pieces/{key}' in the model file")
                atlas.pieces = ChartPieces.from_arrays(arrays)
                if atlas.pieces.n_sub != atlas.n_sub:
                    raise ModelFileError(f"atlas: 'atlas/pieces/first' has {atlas.pieces.n_sub} entries for "
                                         f"{atlas.n_sub} sub-charts")
            if kind == "islands":
                n_layout = atlas.pieces.n if atlas.pieces is not None else atlas.n_sub
                atlas.set_layout(IslandLayout.from_arrays(arrays, n_layout, int(meta["R"]), int(meta["pad"])))
            if "surface" in meta:
                atlas.surface = SurfaceProjection.from_arrays(arrays, meta["surface"])
        except KeyError as e:
            raise ModelFileError(f"atlas: missing entry {e} in the model file") from e
        except (InputError, TypeError, ValueError) as e:
            raise ModelFileError(f"atlas: {e}") from e
        state = {}
        for name, p in atlas.named_parameters():
            key = "textures" if name == "textures" else f"atlas/net/{name}"
            if name == "textures":
                continue
            if key not in arrays:
                raise ModelFileError(f"atlas: missing array '{key}' in the model file")
            a = np.asarray(arrays[key], dtype=np.float32)
            if a.shape != tuple(p.shape):
                raise ModelFileError(f"atlas: array '{key}' has shape {a.shape}, expected {tuple(p.shape)}")
            state[name] = torch.from_numpy(a.copy())
        for key, shape in (("atlas/image", atlas.layout.shape + (3,)), ("atlas/texel_points", atlas.layout.shape + (3,))):
            if key not in arrays or np.asarray(arrays[key]).shape != shape:
                got = np.asarray(arrays[key]).shape if key in arrays else "nothing"
                raise ModelFileError(f"atlas: array '{key}' should have shape {shape}, found {got}")
        try:
            state["textures"] = unpack(torch.from_numpy(np.asarray(arrays["atlas/image"], dtype=np.float32).copy()),
                                       atlas.layout, "atlas/image")[:atlas.textures.shape[0]]
        except InputError as e:
            raise ModelFileError(str(e)) from e
        state["centre"] = atlas.centre
        state["texel_xyz"] = torch.from_numpy(np.asarray(arrays["atlas/texel_points"], dtype=np.float32).copy())
        atlas.load_state_dict(state)
        if "atlas/bake_samples" in arrays:  # optional: older files bake through the texel map alone
            b = np.asarray(arrays["atlas/bake_samples"])
            if b.ndim != 2 or b.shape[1] != 3 or b.shape[0] > MAX_BAKE_SAMPLES or not np.isfinite(b).all():
                raise ModelFileError(f"atlas: array 'atlas/bake_samples' should be finite [S, 3] with S <= "
                                     f"{MAX_BAKE_SAMPLES}, found shape {b.shape}")
            atlas.bake_samples = torch.from_numpy(b.astype(np.float32, copy=True))
            sigma = meta.get("bake_sigma", 1.0)
            if not isinstance(sigma, (int, float)) or not 0 < float(sigma) < 1e3:
                raise ModelFileError(f"atlas: bake_sigma must be a positive number, found {sigma!r}")
            atlas.bake_sigma = float(sigma)
        return atlas.to(device)
