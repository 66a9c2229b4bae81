"""AtlasConfig: every knob of stage 2 (UV charts, distortion loss, texture, packing) in one dataclass."""
from __future__ import annotations

import math
from dataclasses import dataclass

from core.config import opt
from core.util.errors import InputError

# world lengths an atlas stores (the scene's half-size, the anchor planes' bandwidth): outside this range their
# squares and products in float32 / float64 leave the finite numbers (a damaged model file)
WORLD_SCALES = (1e-30, 1e12)
LOOKUPS = ("samples", "charts")  # how frames and the footprint refit read the atlas (EditConfig.lookup)
MAX_CHART_RES = 4096  # texels per chart side: 8 charts of 4096² pack into a 12k x 12k image (1.7 GB of float32 RGB)


@dataclass
class AtlasConfig:
    """Stage 2: learn Nuvo-style UV charts and a packed, paintable texture atlas from surface samples."""

    charts: str = opt("auto", "number of charts: auto (from sample complexity), 4 or 8", choices=("auto", "4", "8"))
    auto_flatness: float = opt(0.3, "auto charts: use 8 when the mean out-of-plane spread of 4 clusters exceeds this",
                               min=0.0)
    sample_colour: str = opt("render", "colour of the surface samples: render (the stage-1 model's object colour of "
                             "the ray; models without an image decoder) or image (the ground-truth pixel, paper)",
                             choices=("render", "image"))
    steps: int = opt(1500, "optimisation steps of the UV maps (joint with the texture)", min=1)
    batch: int = opt(512, "surface samples per step", min=1, max=1 << 22)
    uv_batch: int = opt(128, "random texture coordinates per chart per step (2D->3D->2D cycle, consistency, Chamfer)",
                        min=1, max=1 << 20)
    distortion_batch: int = opt(128, "samples per step on which the Jacobian distortion loss is evaluated",
                                min=1, max=1 << 20)
    lr: float = opt(2e-3, "Adam learning rate of the networks (decays x0.1 over the run)", above=0.0)
    texture_lr: float = opt(3e-2, "Adam learning rate of the chart textures", min=0.0)
    texture_mode: str = opt("kernel", "final texture with the maps frozen: kernel (weighted mean colour of the samples "
                            "around each texel) or descent (texture_steps of Adam on the per-sample MSE)",
                            choices=("kernel", "descent"))
    texture_sigma: float = opt(1.0, "kernel texture: Gaussian std in units of the mean sample spacing in texel space",
                               above=0.0)
    footprint: bool = opt(True, "then refit the texture so that pixel-filtered lookups (2x2 points per pixel, "
                                "as edited frames render) reproduce the training pixels (needs the stage-1 model)")
    footprint_lambda: float = opt(1.0, "footprint refit: pull towards the kernel texture (relative to the data "
                                       "term), when footprint_lambdas is empty or cannot choose (fewer than 4 "
                                       "training views)", min=0.0)
    footprint_lambdas: str = opt("1,4,16,64", "footprint refit: candidate pulls, comma-separated; the one whose fit "
                                              "on the other training views renders every 4th view best is used (one: "
                                              "that λ; empty: footprint_lambda; docs/atlas.md)")
    footprint_lookup: str = opt("samples", "footprint refit: how the refit's frames read the texels, as edited frames "
                                           "do (EditConfig lookup): samples (the nearest stored surface samples' "
                                           "reads) | charts (the chart networks at each point)",
                                choices=LOOKUPS)
    footprint_iters: int = opt(100, "footprint refit: at most this many conjugate-gradient iterations (fewer once "
                                    "converged)", min=0)
    texture_steps: int = opt(300, "descent texture: refinement steps after the maps converge (maps frozen)", min=0)
    width_chart: int = opt(64, "hidden width of the chart-assignment MLP", min=1, max=4096)
    depth_chart: int = opt(3, "hidden layers of the chart-assignment MLP", min=1, max=16)
    width_map: int = opt(96, "hidden width of the texture-coordinate and surface-coordinate MLPs", min=1, max=4096)
    depth_map: int = opt(3, "hidden layers of the texture-coordinate and surface-coordinate MLPs", min=1, max=16)
    fourier_chart: int = opt(1, "Fourier degree of the chart-assignment input encoding", min=0, max=16)
    fourier_map: int = opt(1, "Fourier degree of the map input encodings (reference: 4; 1 measured better at these sizes)",
                           min=0, max=16)
    w_cycle3d: float = opt(1.0, "weight of the 3D->2D->3D cycle loss", min=0.0)
    w_cycle2d: float = opt(1.0, "weight of the 2D->3D->2D cycle loss", min=0.0)
    w_consistency: float = opt(0.04, "weight of the chart-consistency loss -log c_c(s_c(u))", min=0.0)
    w_surface: float = opt(10.0, "weight of the Chamfer surface loss between samples and s_c(u)", min=0.0)
    w_compact: float = opt(0.5, "weight of the cluster-compactness loss", min=0.0)
    w_range: float = opt(1.0, "weight of the UV range hinge", min=0.0)
    w_distortion: float = opt(0.4, "weight of the normal-free distortion loss L_scaling + L_area", min=0.0)
    w_texture: float = opt(1.0, "weight of the colour MSE in the joint map + texture optimisation", min=0.0)
    w_normal: float = opt(0.5, "weight of the normal-flatness loss: the texture coordinates' derivative along each "
                               "sample's surface normal (PCA of its 256 neighbours), squared, in the frame where the "
                               "tangent derivatives are 1, so a texel holds one place of the samples' slab "
                               "(0 = off; the default 0.5 is measured across the scene library in docs/atlas.md)",
                          min=0.0)
    mid_surface: bool = opt(False, "after the maps, project every point onto the samples' mid-surface (anchor planes "
                                   "from the PCA of mid_surface_neighbours samples) before the chart networks — for "
                                   "the texture, the texel map, baking and every lookup alike — so a point's place "
                                   "across the samples' slab does not change its texel (docs/atlas.md)")
    mid_surface_neighbours: int = opt(1024, "mid-surface: samples in each anchor plane's neighbourhood", min=3,
                                      max=4096)
    mid_surface_adaptive: bool = opt(False, "mid-surface: each anchor's neighbourhood is the one of "
                                            "mid_surface_neighbours, 1/2, 1/4 or 1/8 of it that is flattest (spread "
                                            "across / along), so it stops growing at a bend, an edge or a thin part's "
                                            "other face (docs/atlas.md)")
    mid_surface_maps: bool = opt(False, "mid-surface: build it before the maps and fit the maps on the projected "
                                        "samples, with the distortion loss on the Jacobian's part along the "
                                        "mid-surface (its log-area term keeps the map the lookups read from "
                                        "folding); needs mid_surface (docs/atlas.md)")
    w_fold: float = opt(0.0, "mid_surface_maps: weight of the fold barrier — each chart's map keeps one orientation "
                             "against the mid-surface's oriented normals, so no chart lays two parts of the surface "
                             "over each other (0 = off; docs/atlas.md)", min=0.0)
    mid_surface_max_ratio: float = opt(0.7, "mid-surface: an anchor whose neighbourhood's spread across exceeds this "
                                            "share of its spread along the surface (no clear plane: a slab as thick "
                                            "as wide, an edge) leaves points where they are", above=0.0)
    distortion: bool = opt(True, "use the normal-free distortion loss")
    distortion_weighting: str = opt("prob", "weight each chart's distortion by P(c|x) (prob) or not (uniform, paper formula)",
                                    choices=("prob", "uniform"))
    chart_fill: float = opt(0.5, "target fraction of each chart square the surface covers (sets the UV scale)",
                            above=0.0, max=1.0)
    texture_res: int = opt(0, "texels per chart side; 0 = round(256*sqrt(2/n)) as in the paper",
                           min=0, max=MAX_CHART_RES)
    pad: int = opt(4, "grid layout: padding texels around each chart square (edge-replicated, no bleeding)",
                   min=0, max=64)
    layout: str = opt("islands", "packed image: islands (each chart cut to the region the surface uses, packed "
                      "tightly, one chart per point: several times the grid's texels on the surface and every "
                      "texel's point maps back to it, docs/atlas.md) or grid (the paper's fixed chart squares)",
                      choices=("islands", "grid"))
    image_size: int = opt(0, "islands: side of the square atlas image in texels; 0 = chosen per scene from the "
                             "surface area and the training images' pixel footprint on it", min=0, max=MAX_CHART_RES)
    texels_per_pixel: float = opt(5.0, "islands, image_size 0: texels per training-image pixel footprint along the "
                                       "surface (paint finer than the views see; 5 chosen over 4 and 6 on the scene "
                                       "library: hard edges of a retexture hold, docs/atlas.md)", above=0.0,
                                  max=64.0)
    max_image_size: int = opt(2048, "islands: largest automatic atlas side (a coarser texel beyond it)", min=16,
                              max=MAX_CHART_RES)
    island_pad: int = opt(2, "islands: padding texels around each island (islands end up 2 pad - 1 apart; 2: "
                             "bilinear lookups at full resolution read their own island only, no mip level)",
                          min=0, max=64)
    island_fill: float = opt(1.0, "islands: a texel belongs to an island when a sample lands within this many "
                                  "texels of it (closes gaps between samples; in sample spacings when coarser)",
                             above=0.0, max=64.0)
    island_transpose: bool = opt(True, "islands: the packer may transpose an island (turns by 90 degrees and mirrors, "
                                       "exact on the texel grid): curved islands pack much tighter")
    island_packer: str = opt("bitmap", "islands: how islands are packed: bitmap (by their exact cells, largest "
                                       "first, each at its first free spot in reading order in any allowed "
                                       "orientation, other orders where that fails a square: interlocks curved "
                                       "islands; core/atlas/bitmap_pack.py) or "
                                       "xatlas (by their outlines; 5-15 points less utilisation on the library, "
                                       "docs/atlas.md)", choices=("bitmap", "xatlas"))
    island_pack_orders: int = opt(4, "islands, bitmap packer: how many of its greedy placement orders a square is "
                                     "tried with before it counts as too small (1: the largest island first only; "
                                     "core/atlas/bitmap_pack.py ORDERS)", min=1, max=4)
    island_split: float = opt(0.6, "islands: an island longer than this share of the side of the square its "
                                   "islands would fill is cut across (at its narrowest) into pieces that pack into "
                                   "a square; 0 keeps every island whole", min=0.0, max=64.0)
    island_min_fill: float = opt(0.6, "islands (island_split > 0): an island longer than a quarter of that cut "
                                       "length that fills less of its bounding box than this (curved, hollow) is cut "
                                       "too", min=0.0, max=1.0)
    island_sides: bool = opt(True, "islands: split every chart by side — the sign of its map's orientation against "
                                    "the surface's normals given one side picks one of two sub-charts at each "
                                    "point, for baking and lookups alike — so a chart that lays two sides of a part "
                                    "over each other gives each side its own islands (docs/atlas.md)")
    island_sides_step: float = opt(2.0, "island_sides: width of the finite differences that measure the map's "
                                        "orientation, in sample spacings (wider: smoother sides)", above=0.0,
                                   max=64.0)
    island_sides_crease: float = opt(0.0, "island_sides: a point goes to its chart's reversed sub-chart only where "
                                          "the orientation (sine of the angle, in [-1, 1]) is below minus this; "
                                          "creases and points without a normal stay on the majority side",
                                     min=0.0, max=0.99)
    island_sides_min_share: float = opt(0.05, "island_sides: split only the charts with at least this share of "
                                              "their samples on the reversed side (others stay whole: a few "
                                              "reversed samples only add seams; 0 splits every chart that has any; "
                                              "docs/atlas.md)", min=0.0, max=1.0)
    island_sides_anchors: int = opt(20000, "island_sides without mid_surface: anchor planes built for the normals "
                                           "(at most this many)", min=16, max=1 << 20)
    island_sides_neighbours: int = opt(256, "island_sides without mid_surface: samples per anchor plane of the "
                                              "normals (PCA; wider: smoother normals, slower)", min=8,
                                       max=1 << 16)
    island_pieces: bool = opt(True, "islands: cut a (sub-)chart into pieces where its map lays one part of the "
                                     "surface over another with the same orientation (an overlap the side split "
                                     "cannot separate); each piece gets its own islands, a point reads the piece "
                                     "of its nearest patch (docs/atlas.md)")
    island_pieces_voxel: float = opt(4.0, "island_pieces: patch size in sample spacings (the units pieces grow "
                                          "by)", above=0.0, max=64.0)
    island_pieces_far: float = opt(6.0, "island_pieces: patches closer than this many sample spacings never "
                                        "conflict", above=0.0, max=1024.0)
    island_pieces_texels: float = opt(2.0, "island_pieces: a farther patch holding the same texel conflicts only "
                                           "where the map's local linear part would put it more than this many "
                                           "texels away (a map that compresses there is no overlap)", above=0.0,
                                      max=1024.0)
    island_pieces_min_samples: int = opt(200, "island_pieces: smaller pieces join their most connected neighbour",
                                         min=1, max=1 << 24)
    island_min_pixels: float = opt(1.0, "islands: smaller islands are dropped (their points read the nearest "
                                        "island); their area in training-image pixel footprints on the surface "
                                        "(texels_per_pixel^2 texels each: the same surface at any texel density)",
                                   min=0.0, max=1e6)
    texel_max_dist: float = opt(3.0, "texel map: NaN where the texel's surface point is farther than this many sample spacings",
                                above=0.0)
    texel_map: str = opt("splat", "texel map from the forward map (splat: kernel mean of the sample positions around each "
                                   "texel) or the surface-coordinate net (inverse: s_c at texel centres)",
                         choices=("splat", "inverse"))
    texel_max_cycle: float = opt(2.0, "texel map: NaN where t_c of the texel's point misses the texel centre by more than "
                                      "this many texels (folds, outside the used region)", above=0.0)
    island_texel_max_cycle: float = opt(1.0, "islands: the texel map keeps a texel's point only where t_c sends it back "
                                             "within this many texels of the texel centre (the grid uses "
                                             "texel_max_cycle)", above=0.0)
    eval_samples: int = opt(8192, "samples used for the fitting-PSNR history", min=1, max=1 << 22)
    log_every: int = opt(50, "steps between history entries", min=1)
    threads: int = opt(1, "torch CPU threads while fitting (0 = keep torch's setting); small matrices: 2 threads "
                          "on a shared 2-core box took 1611 s where 1 thread takes ~200 s (docs/atlas.md)",
                          min=0, max=1024)
    device: str = opt("auto", "torch device: auto, cpu, cuda")
    seed: int = opt(0, "random seed (same seed, same atlas)", min=0)

    def n_charts(self) -> int | None:
        """The forced chart count, or None for auto."""
        if self.charts == "auto":
            return None
        if self.charts not in ("4", "8"):
            raise InputError(f"AtlasConfig.charts must be 'auto', '4' or '8', got {self.charts!r}")
        return int(self.charts)

    def resolution(self, n: int) -> int:
        """Chart texture side R (paper: 256*sqrt(2/n), so the atlas memory is fixed)."""
        return int(self.texture_res) if self.texture_res > 0 else int(round(256 * math.sqrt(2.0 / n)))

    def lambda_candidates(self) -> list[float]:
        """The footprint refit's candidate λ (footprint_lambdas parsed: finite, >= 0); [] when empty."""
        out = []
        for part in self.footprint_lambdas.replace(" ", "").split(","):
            if not part:
                continue
            try:
                v = float(part)
            except ValueError:
                v = float("nan")
            if not math.isfinite(v) or v < 0:
                raise InputError(f"footprint_lambdas (--atlas-footprint-lambdas): each candidate must be a finite "
                                 f"number >= 0 (comma-separated, e.g. 0.25,1,4,16,64), got {part!r}")
            out.append(v)
        return out

    def max_cycle(self, islands: bool) -> float:
        """Texel map: the largest miss (texels) of a texel's point mapped back, for an island or a grid atlas."""
        return float(self.island_texel_max_cycle if islands else self.texel_max_cycle)
