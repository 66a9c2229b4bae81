"""Render a model after geometry edits (moved / removed / duplicated points) and texture edits (a painted atlas).

Per frame: neighbours are re-selected and attention re-inferred among the deformed points; the point render gives
the base colour; where the atlas was painted, the canonical correspondence maps each ray's surface point back to
canonical space and the painted texture is looked up there. Work a frame does not need is skipped: no
correspondence when the points did not move, no texture work when the atlas is unedited, no attention for rays
with no neighbour (they cannot reach the object).
"""
from __future__ import annotations

import dataclasses
import math

import time
from dataclasses import dataclass

import torch

from core.atlas.config import LOOKUPS
from core.atlas.packing import blend_charts, unpack
from core.atlas.sample_lookup import LOOKUP_K, keeps_samples, sample_lookup
from core.atlas.subpixel import subpixel_chart_uv
from core.config import opt
from core.edits.correspondence import MODES, ray_canonical_points
from core.edits.deformation import (MAX_STRETCH, DeformationConfig, bound_above, det3, expansion_inverse, field_for,
                                     inverse, inverse_at, key_inverse, stretch)
from core.edits.occlusion import REDO_MIN_HIDDEN, front_anchors, front_layer, unoccluded
from core.edits.shading import RESHADE_MIN_RANGE, atlas_shading, reshade_factor
from core.edits.texture_edit import BLEND_THRESHOLD, BLENDS, blend, check_atlas_image, edit_mask
from core.images.colour import linear_to_srgb, srgb_to_linear
from core.images.filter import filter_down, subpixel_points
from core.images.cameras import focal_from_fov, focal_scale, look_at, scaled_focal
from core.points.attention_compiled import attend_compiled, supported
from core.points.neighbors.select import screen_index, select_neighbors
from core.points.render import pixel_grid, shade_frame, trace_frame
from core.points.resolution import (GRID_FILTER_PIXELS, MIN_GRID_SCALE, RENDER_MODES, StretchGrid, check_mode,
                                    decoder_footprint, decoder_scale, filter_sigma, gaussian_blur, interpolate_rays,
                                    interpolate_trace, low_size, points_centre, scale_factor, stretch_grid,
                                    upsample_frame, warp_frame)
from core.points.trace import Trace, held_rows
from core.util.errors import InputError


COMPRESSION = ("tangent", "keep", "undo", "auto")
KEY_STRETCH = ("gap", "full", "sparse", "auto")
DEPTH_REFS = ("nearest", "ray")
FILL_FEATURES = ("blend", "nearer")
FOLD_TESTS = ("displacement", "local-map")
RADIUS_RULES = ("gap", "budget", "frame")
RADIUS_SCALE_MIN = 1.05  # a stretch below this leaves the neighbour search's radius cap as it is


@dataclass
class EditConfig:
    """Edited rendering (correspondence and texture blending)."""

    correspondence: str = opt("deform-gradient", "canonical correspondence: deform-gradient (undoes each "
                                                 "neighbour's local rotation and stretch too) | deform-aware (the "
                                                 "paper's) | naive (the paper's ablation)",
                              choices=MODES)
    f_attention: bool = opt(True, "moved points: measure the attention's key geometry in each neighbour's "
                                  "canonical frame (its inverse local deformation gradient applied to the "
                                  "ray-to-point offset; docs/editing.md has the ablation); rest frames are unchanged")
    f_compression: str = opt("auto", "what the F-aware keys (f_attention; and the deform-gradient correspondence "
                                        "with f_correspondence_compression keys) undo of a local compression: "
                                        "tangent (along the canonical neighbourhood's surface, not across it) | keep "
                                        "(none: stretch only) | undo (all, full F⁻¹) | auto (tangent for a "
                                        "thin-sheet model, undo for one whose points form a thick shell, where no "
                                        "point has a reliable normal: f_thick_spread)",
                             choices=COMPRESSION)
    f_correspondence_compression: str = opt("keep", "what the deform-gradient correspondence undoes of a local "
                                                    "compression: keep (none: rotation and stretch only) | keys "
                                                    "(as the F-aware keys, f_compression) | tangent | undo | "
                                                    "auto (as f_compression's rules)",
                                            choices=("keys",) + COMPRESSION)
    f_thick_spread: float = opt(0.15, "f_compression auto: a model whose median canonical neighbourhood spread "
                                      "(smallest / largest) is at least this is thick: undo, else tangent",
                                min=0.0, max=1.0)
    f_depth: str = opt("nearest", "F-aware keys (f_attention): each neighbour's depth measured from the ray's "
                                  "nearest neighbour in the canonical frames (nearest: as the keys were trained, "
                                  "'depth behind the nearest point') | from the deformed ray's nearest neighbour "
                                  "(ray; a squash or bend reorders the canonical depths along it)",
                       choices=DEPTH_REFS)
    f_radius: bool = opt(True, "moved points: scale the screen neighbour search's pixel radius cap by the points' "
                               "stretch (f_radius_rule)")
    f_radius_rule: str = opt("budget", "f_radius: gap (each point reaches the cap × the largest growth f_fill "
                                       "left between consecutive points on its canonical neighbour pairs where that "
                                       "exceeds f_fill_ratio, else 1; without f_fill its largest local stretch above "
                                       "f_fill_ratio) | budget (gap, counting only the pairs the fill budget kept "
                                       "sparse: pairs grown so far that they got f_fill's most points per pair, a "
                                       "joint's near-tears, reach no farther) | frame (the whole frame's cap × the "
                                       "90th percentile of the points' largest local stretch)", choices=RADIUS_RULES)
    f_reach_gate: float = opt(1.5, "f_radius with rule gap or budget: a ray with no point within this many times "
                                   "the plain pixel radius cap stays empty, so the per-point reach adds far points "
                                   "only to rays near the object (1: rays that already see it; the empty rays around "
                                   "it stop searching there; beyond 1 see f_reach_between); 0 = no gate",
                              min=0.0, max=1e6)
    f_reach_surround: bool = opt(False, "f_reach_gate > 0: a ray with no point within the gate is still reached "
                                        "when the points whose reach covers it surround it (no 3 consecutive of 8 "
                                        "45° sectors around it empty: a hole in a sparse stretched surface, not a "
                                        "ray beside the object's outline; such rays search their whole reach)")
    f_reach_gate_own: bool = opt(False, "f_reach_gate > 1: each point gates at f_reach_gate × the plain cap but "
                                        "at most at its own reach (the wider gate only around points whose "
                                        "neighbours were pulled that far apart)")
    f_reach_between: bool = opt(True, "f_reach_gate > 1: beyond the plain cap the gate opens only for two points "
                                      "within it more than 120° apart as seen from the ray (between the points of "
                                      "a sparse stretched surface, not beside the object's outline)")
    f_reach_perspective: float = opt(16.0, "f_radius with rule gap or budget: a reaching point nearer the camera "
                                           "than the frame's median point reaches farther by the ratio of that "
                                           "median depth to its own, at most this factor (perspective spreads a "
                                           "stretched part near the camera beyond the frame's one pixel cap); its "
                                           "gate widens alike; 0 or 1 = off", min=0.0, max=1e6)
    fold_radius: float = opt(2.0, "moved points: the correspondence keeps only a ray's neighbours whose "
                                  "displacement (canonical − deformed position) lies within this many point spacings "
                                  "of its most-attended neighbour's (drops the other side of a fold, a part swung "
                                  "behind); 0 = keep all (the paper's)", min=0.0, max=1e6)
    fold_test: str = opt("displacement", "fold rule (fold_radius): what it compares between a ray's neighbours: "
                                         "displacement (canonical − deformed position) | local-map (each neighbour's "
                                         "estimate of the ray's canonical point through its own local deformation "
                                         "gradient: a uniform stretch or a rotation drops nothing)",
                         choices=FOLD_TESTS)
    f_fill: bool = opt(True, "moved points: add points along canonical neighbour pairs the pose pulled apart "
                              "(stretched surfaces, a joint's blend band), taking F from the nearer end and "
                              "features as f_fill_features says; rest frames are unchanged")
    f_fill_ratio: float = opt(1.5, "f_fill: a pair whose distance grew by more than this gets points, spaced at most "
                                   "this many times their canonical distance apart", min=1.01, max=100.0)
    f_fill_budget: float = opt(1.0, "f_fill: at most this many added points per point (the ratio is raised past "
                                    "it)", min=0.0, max=64.0)
    f_fill_tear: float = opt(MAX_STRETCH, "f_fill: a canonical neighbour pair grown more than this many times its "
                                          "canonical distance is a tear (parts the pose pulled apart, a rig's envelope "
                                          f"band): it gets no points and counts as closed; above the deformation's "
                                          f"max_stretch ({MAX_STRETCH:g}) that bound applies", min=1.01, max=1e6)
    f_fill_features: str = opt("blend", "f_fill: what an added point carries of its pair's two ends: blend (both "
                                        "ends' features and influence, mixed by where the point lies between them) | "
                                        "nearer (the features and influence of the nearer end)",
                               choices=FILL_FEATURES)
    f_key_stretch: str = opt("auto", "F-aware keys (f_attention) with f_fill: how much of a point's stretch the keys "
                                    "undo: gap (at most the largest growth the fill left between consecutive points "
                                    "on its canonical neighbour pairs: where the fill restored the density, a point "
                                    "reaches no farther than at rest; a neighbourhood the rig tore apart does not "
                                    "spread its points' reach over the background) | sparse (only the growth left "
                                    "where the fill budget kept a pair sparser than f_fill_ratio: where the fill "
                                    "restored the density, none) | full (all of F's stretch) | auto (sparse on a "
                                    "sheet, gap on a thick shell: the model's median spread against "
                                    "f_thick_spread, as f_compression auto)",
                             choices=KEY_STRETCH)
    f_occlusion: bool = opt(True, "moved points: each ray keeps the front one of the surface layers among its "
                                   "neighbours (layers told apart by the points' local deformation gradients: a "
                                   "joint's fold, a part swung behind another); rest frames are unchanged")
    blend: str = opt("soft", "texture-edit blend: soft (m·T' + (1−m)·render) | threshold (paper: m > 0.95)",
                     choices=BLENDS)
    mask_threshold: float = opt(0.01, "a texel counts as painted when its colour changed by more than this (L2)",
                                min=0.0)
    temperature: float = opt(1.0, "attention softmax temperature at render time (< 1 sharpens attention)",
                             min=1e-3, max=1e3)
    colour: str = opt("points", "object colour: points (point render, painted texels from the atlas) | atlas "
                      "(every ray coloured from the atlas texture)", choices=("points", "atlas"))
    attention: str = opt("auto", "attention kernel: auto (compiled on a CPU when numba is installed, else torch) "
                                 "| torch | compiled (the same numbers to float rounding)",
                         choices=("auto", "torch", "compiled"))
    lookup: str = opt("samples", "how a canonical point reads the atlas: samples (the texels its nearest stored "
                                 "surface samples read, where the bake wrote them: docs/atlas.md, 'Lookups through "
                                 "the samples and the fitted bake') | charts (the chart networks' coordinates at "
                                 "the point itself; models without stored samples always use these)",
                      choices=LOOKUPS)
    lookup_k: int = opt(LOOKUP_K, "lookup samples: how many nearest samples a point blends", min=1, max=64)
    antialias: int = opt(2, "texture lookups per pixel side, filtered like Cycles' pixel filter in linear light "
                            "(1 = one lookup at each ray's surface point: cheaper, aliased)", min=1, max=8)
    stretch_grid: float = opt(1.5, "upsampled mode, moved points: where the frame is traced coarser than its "
                                    "pixels and the surface is stretched on the screen at least this many times "
                                    "more along one direction than across it, the training-scale frame is traced "
                                    "on a grid turned to the stretch with as many pixels, spent across it at the "
                                    "screen's own scale and along it the rest (core/points/resolution.py "
                                    "StretchGrid); 0 = off (one scale, from the points' median |det F|)",
                              min=0.0, max=1e6)
    squash_grid: float = opt(1.5, "upsampled mode, moved points: where the frame is traced at the output's pixels "
                                   "and the surface is squashed on the screen, at least this many times more "
                                   "across one direction than along it and this many times below the training "
                                   "scale, the frame is traced on a grid turned to the squash, finer across it "
                                   "(at the training scale, down to squash_grid_finest output pixels), and "
                                   "averaged back over each output pixel (grid_filter; core/points/resolution.py "
                                   "StretchGrid); 0 = off", min=0.0, max=1e6)
    squash_grid_finest: float = opt(0.0625, "the squash grid's finest pixel, in output pixels (its cost: at most "
                                           "1 / this many times the squashed part's pixels)",
                                    min=MIN_GRID_SCALE, max=1.0)
    grid_filter: float = opt(GRID_FILTER_PIXELS, "the pixel filter a squash grid is averaged back with: a tent "
                                                 "this many output pixels to either side of each pixel centre",
                             min=0.0, max=8.0)
    grid_texture: float = opt(0.25, "a squash grid finer than this many output pixels across the squash (a "
                                    "compression of 4x or more on the screen): the painted texture is looked up "
                                    "per grid ray and averaged back over each output pixel with the colour "
                                    "(grid_filter, in linear light) instead of antialias x antialias lookups per "
                                    "pixel; 0 = off", min=0.0, max=1.0)
    reshade: str = opt("off", "moved points of a lit model: re-shade each object ray by S(posed normal) / S(rest "
                              "normal), S a shading of the normal fitted to the atlas's colours "
                              "(core/edits/shading.py; docs/editing.md 'Lit scenes'): off | auto (where the fitted "
                              "shading's log range reaches RESHADE_MIN_RANGE, the lit models measured) | on",
                       choices=("off", "auto", "on"))
    render_mode: str = opt("auto", "frames finer than the training pixels (core/points/resolution.py): pixels | "
                                   "filtered | footprint | decoder | interior | their '+' pairs | upsampled; "
                                   "auto = the model's (upsampled for a single-scale fit; for a multi-scale fit "
                                   "interior+filtered where its fit measured it better, else filtered)",
                           choices=("auto", *RENDER_MODES))


# a squash grid holds at most this many times the output frame's pixels (its pixels are coarsened to fit)
SQUASH_GRID_MAX_PIXELS = 4.0
# a pixel takes its texture from the squash grid's lookups (`_grid_lookup`) where grid rays on the object hold at
# least this share of its filter, else from its own lookups (a silhouette pixel the grid's object barely reaches)
GRID_LOOKUP_MIN_WEIGHT = 0.05

SCREEN_STRETCH_SAMPLES = 2048  # points the screen stretch's median is taken over (evenly spaced beyond)


def _rows_then_blend(x: torch.Tensor, given: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
                     t: torch.Tensor) -> torch.Tensor:
    """x [N, ...] -> [G + P, ...]: the rows `given` [G], then x[a] (1 − t) + x[b] t for the pairs a, b [P] (t [P]
    shaped to broadcast over x's rows), written into one tensor."""
    out = x.new_empty((given.shape[0] + a.shape[0], *x.shape[1:]))
    torch.index_select(x, 0, given, out=out[:given.shape[0]])
    torch.add(x[a].mul_(1 - t), x[b].mul_(t), out=out[given.shape[0]:])
    return out


class EditState:
    """Per-model edit inputs, validated once and reused across frames (animation, live preview).

    points [M, 3] deformed positions (None = canonical), ids [M] canonical index of each point (None = identity,
    requires M == N), atlas [H, W, 3] painted atlas (None = unedited). Non-finite positions (a broken rig) are
    counted and treated as absent points. With f_fill, points and ids (and F) grow by the added points
    (`filled_points`, appended after the given ones).
    paint_from: an earlier state of the same model, atlas and texture settings (a new pose of one painted
    object): its prepared painted textures are reused instead of checking, comparing and unpacking the atlas
    again (`atlas` is then not read; the caller vouches that it is the same image). Ignored when the model or the
    colour / mask_threshold settings differ.
    """

    def __init__(self, bundle, points=None, ids=None, atlas=None, cfg: EditConfig | None = None,
                 deformation: DeformationConfig | None = None, paint_from: "EditState | None" = None):
        self.bundle = bundle
        self.cfg = cfg or EditConfig()
        self.deformation_cfg = deformation or DeformationConfig()
        self._f = self._inv_f = self._inv_f_keys = self._radius_scale = self._reach = None
        self._row_tables = {}  # name -> ([M, 3, 3] rows filled as frames need them, [M] bool: which are filled)
        self._f_source = None  # f_fill: per row of F the given row it copies ([M] long; None: no row was added)
        self._local_scale = None  # median |det F|^(1/3), once computed
        self._grid = None  # (camera key, StretchGrid or None) of the last frame `_stretched` was asked for
        self._centre = None  # the points' centre, once computed
        self._fill_blend = None  # f_fill_features = blend: (canonical ids of both ends [P], fraction [P])
        self._gap = None  # f_fill: per point the largest growth left between consecutive points on its pairs
        self._sparse = None  # f_fill: that growth where the budget kept a pair sparser than f_fill_ratio, else 1
        self.deformation_seconds = 0.0  # time spent on F and what derives from it (0 until it is needed)
        self.fit_seconds = 0.0  # of which the fit of F
        if not 1 <= int(self.cfg.antialias) <= 8:
            raise InputError(f"antialias: texture lookups per pixel side must be 1-8, got {self.cfg.antialias}")
        model = bundle.model
        dev = model.xyz.device
        n = model.num_points
        if points is None and ids is not None:
            raise InputError("ids were given without points: pass the deformed positions they belong to")
        self.moved = points is not None
        if points is None:
            self.points = model.xyz.detach()
            self.ids = None
        else:
            pts = torch.as_tensor(points)
            if pts.dim() != 2 or pts.shape[1] != 3:
                raise InputError(f"points: expected shape [M, 3], got {tuple(pts.shape)}")
            pts = pts.to(dev, torch.float32)
            if pts.shape[0] == 0:
                raise InputError("points: the point set is empty (0 positions); there is nothing to render")
            if ids is None:
                if pts.shape[0] != n:
                    raise InputError(f"points: {pts.shape[0]} positions for a model of {n} points and no ids; "
                                     "pass ids (the canonical index of each point) when points were added or removed")
                self.ids = None
            else:
                idt = torch.as_tensor(ids)
                if idt.dim() != 1 or idt.shape[0] != pts.shape[0]:
                    raise InputError(f"ids: expected shape [{pts.shape[0]}] (one per point), got {tuple(idt.shape)}")
                if idt.dtype.is_floating_point or idt.dtype == torch.bool:
                    raise InputError(f"ids: expected integers, got {idt.dtype}")
                idt = idt.to(dev, torch.long)
                if idt.numel() and (int(idt.min()) < 0 or int(idt.max()) >= n):
                    raise InputError(f"ids: values must lie in [0, {n - 1}] for this model, found "
                                     f"[{int(idt.min())}, {int(idt.max())}]")
                self.ids = idt
            self.points = pts
        self.non_finite_points = int((~torch.isfinite(self.points).all(1)).sum())
        if self.moved and self.ids is None and torch.equal(self.points, model.xyz.detach()):
            self.moved = False  # same positions as canonical: nothing to correspond
        self.filled_points = 0  # points f_fill added (after the given ones)
        fill_can = None
        if self.moved and self.cfg.f_fill and self.cfg.f_fill_budget > 0:
            fill_can = self._fill()
        self.p_can = model.xyz.detach() if self.ids is None else model.xyz.detach()[self.ids]
        if fill_can is not None:  # added points sit between their pair's canonical points, not on their source
            self.p_can = torch.cat([self.p_can[:self.p_can.shape[0] - fill_can.shape[0]], fill_can])
        feats, infl = model.features.detach(), model.influence.detach()
        if self._fill_blend is not None:  # f_fill_features = blend: added points mix their pair's two ends
            a, b, t = self._fill_blend
            given = self.ids[:self.ids.shape[0] - t.shape[0]]
            self.features = _rows_then_blend(feats, given, a, b, t.to(feats.dtype)[:, None])
            self.influence = _rows_then_blend(infl, given, a, b, t.to(infl.dtype))
        else:
            self.features = None if self.ids is None else feats[self.ids]
            self.influence = infl if self.ids is None else infl[self.ids]
        self.atlas_image = None
        self.mask_image = None
        self._edit_textures = None
        self._sample_reads = None
        if not self._reuse_paint(paint_from):
            self._prepare_paint(atlas)

    def _prepare_paint(self, atlas) -> None:
        """The painted atlas checked against the model's, its changed texels as a mask (none: no texture work),
        or for colour 'atlas' the whole atlas."""
        dev = self.bundle.model.xyz.device
        atl = self.bundle.atlas
        if atlas is not None:
            if atl is None:
                raise InputError("an edited atlas was given but this model has no atlas; run `pointgt atlas` first")
            original = atl.packed_image().to(dev)
            img = check_atlas_image(atlas, tuple(original.shape[:2])).to(dev)
            mask = edit_mask(original, img, self.cfg.mask_threshold)
            if bool(mask.any()):  # unedited atlas: skip all texture work
                self.atlas_image = img
                self.mask_image = mask[..., None].expand(-1, -1, 3).contiguous()
        if self.cfg.colour == "atlas":
            if atl is None:
                raise InputError("colour 'atlas' needs a model with an atlas; run `pointgt atlas` first")
            if self.atlas_image is None:
                self.atlas_image = atl.packed_image().to(dev)
            self.mask_image = torch.ones_like(self.atlas_image)

    def _reuse_paint(self, other: "EditState | None") -> bool:
        """Take `other`'s prepared atlas and mask images and per-chart textures (see paint_from); False when
        `other` is None or differs in model or texture settings."""
        if other is None or other.bundle is not self.bundle or other.cfg.colour != self.cfg.colour \
                or other.cfg.mask_threshold != self.cfg.mask_threshold:
            return False
        if other._edit_textures is None and other.atlas_image is not None:
            _ = other.edit_textures  # unpacked once, for every state that shares them
        self.atlas_image, self.mask_image = other.atlas_image, other.mask_image
        self._edit_textures = other._edit_textures
        if other.cfg.lookup == self.cfg.lookup and other.atlas_image is not None and other.sample_lookup is not None:
            self._sample_reads = other.sample_reads  # read once, for every state that shares the paint
        return True

    def _fill(self) -> torch.Tensor | None:
        """f_fill: fit F on the given points, add points where neighbour pairs were pulled apart
        (DeformationField.fill) and extend points, ids and F with them. Returns their canonical positions [P, 3]
        (None when nothing was added)."""
        fld = field_for(self.bundle.model, self.deformation_cfg)
        f, (new, can, src, partner, frac, gap, sparse) = self._timed(lambda: fld.gradients_and_fill(
            self.points, self.ids, ratio=self.cfg.f_fill_ratio, budget=self.cfg.f_fill_budget, with_partner=True,
            with_gap=True, gap_pairs="budget" if self.cfg.f_radius_rule == "budget" else "all",
            tear=self.cfg.f_fill_tear))
        self._f = f
        self._gap = gap
        self._sparse = sparse
        self.fit_seconds = self.deformation_seconds
        if new.shape[0] == 0:
            return None
        m = self.points.shape[0]
        ids = torch.arange(m, device=self.points.device) if self.ids is None else self.ids
        self.points = torch.cat([self.points, new.to(self.points.dtype)])
        self.ids = torch.cat([ids, ids[src]])
        self._f = torch.cat([f, f[src]])
        self._f_source = torch.cat([torch.arange(m, device=src.device), src])
        self._gap = torch.cat([gap, torch.maximum(gap[src], gap[partner])])
        self._sparse = torch.cat([sparse, torch.maximum(sparse[src], sparse[partner])])
        self.filled_points = int(new.shape[0])
        if self.cfg.f_fill_features == "blend":
            self._fill_blend = (ids[src], ids[partner], frac)
        return can

    @torch.no_grad()
    def _timed(self, fn):
        t0 = time.perf_counter()
        out = fn()
        self.deformation_seconds += time.perf_counter() - t0
        return out

    @property
    def f(self) -> torch.Tensor | None:
        """Local deformation gradients of the points [M, 3, 3] (None when nothing moved), fitted on first use from
        the model's cached canonical neighbourhoods (core/edits/deformation.py)."""
        if not self.moved:
            return None
        if self._f is None:
            self._f = self._timed(lambda: field_for(self.bundle.model, self.deformation_cfg).gradients(self.points,
                                                                                                      self.ids))
            self.fit_seconds = self.deformation_seconds
        return self._f

    @property
    def inv_f(self) -> torch.Tensor | None:
        """F⁻¹ [M, 3, 3] (None when nothing moved)."""
        if self.f is None:
            return None
        if self._inv_f is None:
            self._inv_f = self._timed(lambda: inverse(self._f))
        return self._inv_f

    def inv_f_at(self, rows: torch.Tensor) -> torch.Tensor | None:
        """`inv_f` where only the rows [P] long are read: [M, 3, 3], F⁻¹ at those rows and at any computed before
        (each row as in `inv_f`), zero at the others (the occlusion rule reads only the points a frame's
        rays hold). None when nothing moved."""
        if self.f is None:
            return None
        if self._inv_f is not None:
            return self._inv_f
        return self._rows_filled("inv_f", rows, lambda todo, table: inverse_at(self._f, todo, table), of_f=True)

    def _rows_filled(self, name: str, rows: torch.Tensor, fill, of_f: bool = False) -> torch.Tensor:
        """The [M, 3, 3] table `name` of this state with the rows [P] long filled: fill(todo [Q] long, table) writes
        the rows not filled before (timed as deformation work); the other rows stay 0 until a frame reads them.
        of_f: each row is a function of that row of F alone, so a row f_fill added (a copy of its source's F)
        copies its source's row instead of being computed again (the same numbers)."""
        if name not in self._row_tables:
            self._row_tables[name] = (torch.zeros_like(self._f),
                                      torch.zeros(self._f.shape[0], dtype=torch.bool, device=self._f.device))
        table, done = self._row_tables[name]
        todo = rows[~done[rows]]
        if not todo.numel():
            return table
        if of_f and self._f_source is not None:
            self._timed(lambda: self._fill_by_source(todo, table, done, fill))
        else:
            self._timed(lambda: fill(todo, table))
        done[todo] = True
        return table

    def _fill_by_source(self, todo: torch.Tensor, table: torch.Tensor, done: torch.Tensor, fill) -> None:
        """`_rows_filled`'s of_f case: fill the sources of the rows todo [Q] that are not filled yet (each once),
        then copy them into the added rows among todo."""
        source = self._f_source[todo]
        need = torch.zeros_like(done)
        need[source] = True
        base = torch.nonzero(need & ~done).squeeze(1)
        if base.numel():
            fill(base, table)
            done[base] = True
        copy = source != todo
        if bool(copy.any()):
            table[todo[copy]] = table[source[copy]]

    @property
    def inv_f_keys(self) -> torch.Tensor | None:
        """The inverse gradients the deform-gradient correspondence (and the local-map fold test) use [M, 3, 3], by
        f_compression: undo = F⁻¹; keep = the inverse of F with its singular values raised to at least 1 (rotation
        and stretch undone, compression kept); tangent = the inverse of G = F + (max(|F n|, 1)/|F n| − 1) F n nᵀ,
        n the canonical neighbourhood's normal (least-spread direction): F as it is along the surface, its
        compression across it not undone; auto = one of tangent and undo by the model (`compression`). None when
        nothing moved."""
        if self.f is None:
            return None
        if self.compression == "undo":
            return self.inv_f
        if self._inv_f_keys is None:
            self._inv_f_keys = self._timed(lambda: self._rule_inverse(None))
        return self._inv_f_keys

    @property
    def inv_f_correspondence(self) -> torch.Tensor | None:
        """The inverse gradients the deform-gradient correspondence uses [M, 3, 3]: `inv_f_keys`, or by
        f_correspondence_compression's own rule when it is not keys (auto resolved by the model's thickness, as
        `compression`). None when nothing moved."""
        if self.f is None:
            return None
        return self.inv_f_correspondence_at(torch.arange(self._f.shape[0], device=self._f.device))

    def inv_f_correspondence_at(self, rows: torch.Tensor) -> torch.Tensor | None:
        """`inv_f_correspondence` where only the rows [P] long are read: [M, 3, 3], right at those rows and at any
        computed before, zero at the others (a frame's correspondence reads only its rays' neighbours); the
        keys' and the undo rules give their whole tables. None when nothing moved."""
        if self.f is None:
            return None
        mode = self.cfg.f_correspondence_compression
        if mode != "keys":
            mode = self._compression_rule(mode)
        if mode in ("keys", self.compression):
            return self.inv_f_keys
        if mode == "undo":
            return self.inv_f

        def fill(todo, table):
            table[todo] = self._rule_inverse(None, todo, mode=mode)
        return self._rows_filled("inv_f_correspondence", rows, fill, of_f=True)

    @property
    def inv_f_attention(self) -> torch.Tensor | None:
        """The inverse gradients the attention keys use [M, 3, 3]: `inv_f_keys`, but with f_key_stretch gap (and
        f_fill) that of F with each point's singular values capped at the largest growth the fill left between
        consecutive points on its canonical neighbour pairs (1 where nothing grew): the keys undo the stretch the
        points' spacing still shows, not more; with sparse, capped at that growth only on the pairs the fill budget
        left sparser than f_fill_ratio (1 elsewhere); auto: `key_stretch`. None when nothing moved."""
        if self.f is None:
            return None
        return self.inv_f_attention_at(torch.arange(self._f.shape[0], device=self._f.device))

    def inv_f_attention_at(self, rows: torch.Tensor) -> torch.Tensor | None:
        """`inv_f_attention` where only the rows [P] long (distinct) are read: [M, 3, 3], right at those rows and at
        any computed before, zero at the others (a frame's attention reads only the points its rays hold, often far
        fewer than all: those out of view, or of a frame traced at the training scale). None when nothing moved."""
        if self.f is None:
            return None
        if self.cfg.f_key_stretch == "full" or self._gap is None:
            return self.inv_f_keys
        cap = self._sparse if self.key_stretch == "sparse" else self._gap

        def fill(todo, table):
            table[todo] = self._rule_inverse(cap, todo)
        return self._rows_filled("inv_f_attention", rows, fill)

    def _rule_inverse(self, cap: torch.Tensor | None, rows: torch.Tensor | None = None,
                      mode: str | None = None) -> torch.Tensor:
        """The compression rule `mode` (default `compression`: the keys') applied to F with its singular values
        capped at cap [M] (None: none): its inverse [M, 3, 3] (`key_inverse`, compiled); given rows [P] long, of
        those rows only [P, 3, 3] (each row is computed on its own: the same values)."""
        f = self._f if rows is None else self._f[rows]
        if cap is not None and rows is not None:
            cap = cap[rows]
        ids = self.ids if rows is None else (rows if self.ids is None else self.ids[rows])
        mode = mode or self.compression
        if mode == "keep":
            return expansion_inverse(f if cap is None else bound_above(f, cap))
        n = None if mode == "undo" else field_for(self.bundle.model, self.deformation_cfg).normals(ids)
        return key_inverse(f, cap, n)

    @property
    def key_stretch(self) -> str:
        """The keys' stretch rule: f_key_stretch, with auto resolved by the model's thickness as `compression` is
        (gap for a thick shell, sparse for a sheet)."""
        mode = self.cfg.f_key_stretch
        if mode != "auto":
            return mode
        return "gap" if self._thick() else "sparse"

    def _thick(self) -> bool:
        """Whether the model's points form a thick shell (median spread of the canonical neighbourhoods at least
        f_thick_spread) rather than a sheet."""
        return field_for(self.bundle.model, self.deformation_cfg).median_spread >= self.cfg.f_thick_spread

    @property
    def compression(self) -> str:
        """The compression rule the keys use: f_compression, with auto resolved by the model's thickness
        (`DeformationField.median_spread` against f_thick_spread: undo for a thick shell, tangent for a sheet)."""
        return self._compression_rule(self.cfg.f_compression)

    def _compression_rule(self, mode: str) -> str:
        """A compression rule (COMPRESSION) with auto resolved by the model's thickness: undo for a thick shell,
        tangent for a sheet."""
        if mode != "auto":
            return mode
        return "undo" if self._thick() else "tangent"

    @property
    def rebase_depth(self) -> bool:
        """Whether the F-aware keys take depths from the ray's nearest neighbour in the canonical frames (f_depth
        nearest; `PointModel.attend`): only for moved points with f_attention."""
        return bool(self.moved and self.cfg.f_attention and self.cfg.f_depth == "nearest")

    @property
    def centre(self) -> torch.Tensor:
        """The points' centre [3] (`points_centre`: the mean of the finite ones), once per state."""
        if self._centre is None:
            self._centre = points_centre(self.points.detach())
        return self._centre

    @property
    def local_scale(self) -> float:
        """How much larger the moved points are than their canonical neighbourhoods: the median over the finite
        points of |det F|^(1/3) (an object scaled by s: s; a bend: about 1); 1 when nothing moved or undefined."""
        if self.f is None:
            return 1.0
        if self._local_scale is None:  # once per state: render_edited asks twice a frame
            det = det3(self._f.double()).abs()[torch.isfinite(self.points).all(1)]
            det = det[torch.isfinite(det) & (det > 0)]
            s = float(det.median() ** (1.0 / 3.0)) if det.numel() else 1.0
            self._local_scale = s if math.isfinite(s) and s > 0 else 1.0
        return self._local_scale

    def screen_stretch(self, c2w: torch.Tensor) -> tuple[float, float, float]:
        """How the moved points' local maps stretch the surface on the screen of camera c2w [4, 4]: (along,
        across, angle), the square roots of the eigenvalues of the median (over the finite points, up to
        SCREEN_STRETCH_SAMPLES of them evenly spaced) of (P F)(P F)ᵀ (P [2, 3] the camera's image axes: the
        outline of a canonical unit ball as the camera sees it deformed, orthographically), along ≥ across, and the
        angle of the along direction (radians from the image's x axis towards its up axis, in (−π/2, π/2]: a grid
        turned by it stays upright). (1, 1, 0) when nothing moved; a rigid motion gives (1, 1, ·)."""
        if self.f is None:
            return 1.0, 1.0, 0.0
        p = c2w[:3, :2].T.to(self._f.device, self._f.dtype)  # [2, 3]: the camera's x and up axes
        step = max(1, self._f.shape[0] // SCREEN_STRETCH_SAMPLES)  # every step-th point: a median needs no more
        a = torch.einsum("ij,mjk->mik", p, self._f[::step])  # [M', 2, 3]
        g = torch.stack([(a[:, 0] * a[:, 0]).sum(1), (a[:, 0] * a[:, 1]).sum(1), (a[:, 1] * a[:, 1]).sum(1)], 1)
        g = g[torch.isfinite(self.points[::step]).all(1) & torch.isfinite(g).all(1)]
        if not g.shape[0]:
            return 1.0, 1.0, 0.0
        xx, xy, yy = (float(v) for v in g.median(0).values.double())
        evals, evecs = torch.linalg.eigh(torch.tensor([[xx, xy], [xy, yy]], dtype=torch.float64))  # ascending
        along, across = (math.sqrt(max(float(v), 0.0)) for v in (evals[1], evals[0]))
        angle = math.atan2(float(evecs[1, 1]), float(evecs[0, 1]))
        angle = angle - math.pi if angle > 0.5 * math.pi else angle + math.pi if angle <= -0.5 * math.pi else angle
        if not (math.isfinite(along) and math.isfinite(across) and math.isfinite(angle)):
            return 1.0, 1.0, 0.0
        return along, across, angle

    @property
    def radius_scale(self) -> float:
        """Factor on the neighbour search's pixel radius cap for these points: the 90th percentile of the largest
        local stretch, 1 when nothing moved or it is below RADIUS_SCALE_MIN."""
        if self.f is None:
            return 1.0
        if self._radius_scale is None:
            def scale():
                st = stretch(self._f)[torch.isfinite(self.points).all(1)]
                q = float(torch.quantile(st, 0.9)) if st.numel() else 1.0
                return q if q > RADIUS_SCALE_MIN else 1.0
            self._radius_scale = self._timed(scale)
        return self._radius_scale

    @property
    def reach(self) -> torch.Tensor | None:
        """Per-point factor on the neighbour search's pixel radius cap [M] (f_radius_rule "gap"): the growth the
        fill left between consecutive points on the point's canonical neighbour pairs where it exceeds
        f_fill_ratio (without f_fill: its largest local stretch where above f_fill_ratio), else 1; None when
        nothing moved."""
        if self.f is None:
            return None
        if self._reach is None:
            def reach():
                if self._sparse is not None:
                    g = self._sparse.double()
                    return torch.where(g > self.cfg.f_fill_ratio, g, torch.ones_like(g))
                st = torch.nan_to_num(stretch(self._f).double(), nan=1.0, posinf=1.0, neginf=1.0)
                return torch.where(st > self.cfg.f_fill_ratio, st, torch.ones_like(st))
            self._reach = self._timed(reach)
        return self._reach

    def search_radius(self) -> tuple[float, torch.Tensor | None]:
        """(radius_scale, reach) the neighbour search of these points takes by f_radius and f_radius_rule: (1, None)
        with f_radius off or nothing moved."""
        if not (self.cfg.f_radius and self.moved):
            return 1.0, None
        if self.cfg.f_radius_rule == "frame":
            return self.radius_scale, None
        return 1.0, self.reach

    @property
    def reach_gate(self) -> float:
        """The gate of the neighbour search's per-point reach (`trace_frame(reach_gate=...)`): f_reach_gate with a
        reach in use, else 0 (none)."""
        return float(self.cfg.f_reach_gate) if self.search_radius()[1] is not None else 0.0

    @property
    def reach_surround(self) -> bool:
        """Whether the gate lets rays its neighbours surround through (`trace_frame(reach_surround=...)`)."""
        return bool(self.cfg.f_reach_surround) and self.reach_gate > 0

    @property
    def reach_gate_own(self) -> bool:
        """Whether each point's gate is at most its own reach (`trace_frame(reach_gate_own=...)`)."""
        return bool(self.cfg.f_reach_gate_own) and self.reach_gate > 0

    @property
    def reach_perspective(self) -> float:
        """The largest perspective factor on a reaching point's reach (`trace_frame(reach_perspective=...)`):
        f_reach_perspective with a reach in use, else 0 (none)."""
        return float(self.cfg.f_reach_perspective) if self.search_radius()[1] is not None else 0.0

    @property
    def reach_between(self) -> bool:
        """Whether beyond the plain cap the gate opens only between points (`trace_frame(reach_between=...)`)."""
        return bool(self.cfg.f_reach_between) and self.reach_gate > 0

    def share_deformation(self, other: "EditState") -> None:
        """Reuse `other`'s fitted F (same model, points and ids: e.g. several edits of one pose) and the time the
        fit took; what this state derives from F is computed (and timed) here."""
        if (other.moved and self.moved and other._f is not None and self._f is None and other.filled_points == 0
                and self.filled_points == 0):
            self._f = other._f
            self.fit_seconds = self.deformation_seconds = other.fit_seconds

    def search_index(self, c2w: torch.Tensor, height: int, width: int, focal, k: int | None = None):
        """The screen neighbour index these points are traced with (core/points/neighbors/select.py
        `screen_index`: the model's method and cap, K = k or the model's, the f_radius scale) when the occlusion
        rule may search rays again, so `trace_frame(index=...)` and `visible_layer(index=...)` project the points
        once; None when it will not (nothing moved, the rule off) or the search has no screen (perpendicular)."""
        if not (self.moved and self.cfg.f_occlusion):
            return None
        return self._screen_index(c2w, height, width, focal, k or self.bundle.model.cfg.k)

    def _screen_index(self, c2w, height, width, focal, k):
        model, pts = self.bundle.model, self.points
        search = torch.where(torch.isfinite(pts).all(dim=1)[:, None], pts, torch.full_like(pts, float("nan")))
        radius_scale, reach = self.search_radius()
        return screen_index(search, model.cfg.neighbors, k, c2w.to(pts.device, torch.float32), height, width, focal,
                            model.cfg.neighbor_radius_px, radius_scale=radius_scale, reach=reach,
                            reach_gate=self.reach_gate, reach_surround=self.reach_surround,
                            reach_gate_own=self.reach_gate_own, reach_between=self.reach_between,
                            reach_perspective=self.reach_perspective)

    def visible_layer(self, trace: Trace, c2w: torch.Tensor | None = None, focal=None, index=None) -> Trace:
        """f_occlusion: the trace of these points with each ray's attention kept on its front surface layer
        (core/edits/occlusion.py); the trace itself when the points did not move or the rule is off.

        trace: `trace_frame` of these points (their keys, influence and radius as render_edited traces them) with
        the camera c2w [4, 4] and focal it was traced with, owned by the caller (with the camera, the redone rays
        are written into its tensors): a ray whose neighbours reach behind its front layer
        gets its K neighbours again from the ranked candidates the front layer does not hide (twice K searched
        within the first search's pixel radius), and its attention anew over them, so hidden points neither take
        its neighbour slots nor its colour. index: the trace's own `search_index` (else it is built again).
        Without the camera (or for a trace with footprint windows) the hidden neighbours' weights are dropped
        instead."""
        if not (self.moved and self.cfg.f_occlusion):
            return trace
        return self._timed(lambda: self._visible_layer(trace, c2w, focal, index))

    def _visible_layer(self, trace: Trace, c2w, focal, index=None) -> Trace:
        model = self.bundle.model
        spacing = float(model.spacing)
        if c2w is None or focal is None:
            return front_layer(trace, self.points, self.p_can, self.inv_f, spacing)
        inv_f = self.inv_f_at(trace.held)  # the redo reads only its anchors'
        front = front_anchors(trace, self.points, self.p_can, inv_f, spacing, min_hidden=REDO_MIN_HIDDEN)
        if front is None:
            return trace
        rows, anchor, depth, _ = front
        height, width = trace.shape
        k = trace.idx.shape[1]
        cfg = self.cfg
        pts = self.points
        finite = torch.isfinite(pts).all(dim=1)
        search = torch.where(finite[:, None], pts, torch.full_like(pts, float("nan")))
        o, d = trace.origins[rows], trace.dirs[rows]
        if index is None:
            index = self._screen_index(c2w, height, width, focal, k)
        cand = select_neighbors(search, model.cfg.neighbors, 2 * k, c2w.to(pts.device, torch.float32), height, width,
                                focal, pixel_grid(height, width, pts.device)[rows], o, d, index=index)
        idx = unoccluded(cand, anchor, depth, o, d, pts, self.p_can, inv_f, spacing, k)
        keys = self.inv_f_attention_at(held_rows(idx, pts.shape[0])) if cfg.f_attention else None
        pts_math = torch.where(finite[:, None], pts, torch.zeros_like(pts))
        if cfg.attention != "torch" and supported(model, pts.device):  # as trace_frame chooses
            att = attend_compiled(model, pts_math, self.influence, o, d, idx, temperature=cfg.temperature, inv_f=keys,
                                  rebase_depth=self.rebase_depth)
        else:
            att = model.attend(pts_math, self.influence, o, d, idx, temperature=cfg.temperature, inv_f=keys,
                               rebase_depth=self.rebase_depth)
        # the redone rows are written into the trace's own tensors (its only holder is `_trace`, which built it for
        # this call: copying five frame-sized arrays cost more than the rows' search); a new Trace object, so a
        # depth computed before follows the new x
        trace.idx[rows] = idx
        for name in ("weights", "fg_weights", "bg", "x"):
            t = getattr(trace, name)
            t[rows] = att[name].to(t.dtype)
        return dataclasses.replace(trace)

    def canonical_surface(self, trace: Trace, sel: torch.Tensor) -> torch.Tensor:
        """Canonical surface points [S, 3] of the rays sel [S] of a trace of these points, by the configured
        correspondence (core.edits.correspondence.ray_canonical_points, with the fold rule of cfg.fold_radius; F is
        fitted only when the mode needs it).
        A trace interpolated from the training scale (`Trace.coarse`, the `upsampled` mode) blends the canonical
        points of its training-scale rays with the interpolation's weights, so they vary smoothly across a
        training pixel in every correspondence.
        Can be non-finite where the correspondence breaks down."""
        if trace.coarse is not None:
            link = trace.coarse
            need = link.corners[sel][link.weights[sel] > 0].unique()
            low_can = torch.zeros(link.low.x.shape, dtype=trace.x.dtype, device=trace.x.device)
            if need.numel():
                low_can[need] = self.canonical_surface(link.low, need).to(low_can.dtype)
            return interpolate_rays(link, low_can, sel)
        if not self.moved:  # the ray's surface point on its ray, as the atlas saw it
            return ray_canonical_points(trace, sel)
        cfg = self.cfg
        mode = cfg.correspondence
        fold = cfg.fold_radius * float(self.bundle.model.spacing) if cfg.fold_radius > 0 else None
        local = fold is not None and cfg.fold_test == "local-map"
        inv_f = None
        if mode == "deform-gradient":  # only the rows the rays' neighbours hold
            inv_f = self.inv_f_correspondence_at(held_rows(trace.idx[sel], self.p_can.shape[0]))
        return ray_canonical_points(trace, sel, self.points, self.p_can, mode, inv_f=inv_f, fold_radius=fold,
                                    fold_inv_f=self.inv_f_keys if local else None)

    @property
    def textured(self) -> bool:
        return self.atlas_image is not None

    @property
    def edit_textures(self) -> torch.Tensor:
        """Painted texture and its mask per chart, stacked: [n, 4, R, R] (rgb, mask; one bilinear lookup serves
        both)."""
        if self._edit_textures is None:
            layout = self.bundle.atlas.layout
            rgb, mask = unpack(self.atlas_image, layout), unpack(self.mask_image, layout)[:, :1]
            if self.bundle.atlas.islands:  # n views of one image: stack the image once, not n copies of it
                self._edit_textures = torch.cat([rgb[:1], mask[:1]], 1).contiguous().expand(rgb.shape[0], -1, -1, -1)
            else:
                self._edit_textures = torch.cat([rgb, mask], 1).contiguous()
        return self._edit_textures

    @property
    def sample_lookup(self):
        """The atlas's SampleLookup when lookups go through the samples (EditConfig lookup samples and the atlas
        keeps samples), else None (chart lookups)."""
        atlas = self.bundle.atlas
        return sample_lookup(atlas) if self.cfg.lookup == "samples" and keeps_samples(atlas) else None

    @property
    def sample_reads(self) -> torch.Tensor:
        """What every stored sample reads of the painted texture and its mask [S, 4], once per state."""
        if self._sample_reads is None:
            self._sample_reads = self.sample_lookup.read(self.edit_textures)
        return self._sample_reads


def _lookup(state: EditState, x: torch.Tensor, texture_fn=None) -> torch.Tensor:
    """Painted colour and mask at canonical points x [M, 3] -> [M, 4] (rgb, mask); texture_fn(x) -> rgb [M, 3]
    replaces the atlas (mask 1), e.g. a procedural texture evaluated exactly (the perfect-atlas reference)."""
    if texture_fn is not None:
        rgb = texture_fn(x).to(x.dtype)
        return torch.cat([rgb, torch.ones_like(rgb[:, :1])], 1)
    if state.sample_lookup is not None:
        return _sample_painted(state, x)
    return _painted(state, *state.bundle.atlas.chart_uv(x))


def _sample_painted(state: EditState, x: torch.Tensor) -> torch.Tensor:
    """Painted colour and mask [M, 4] at canonical points x [M, 3] through the nearest stored samples (EditConfig
    lookup samples)."""
    atlas = state.bundle.atlas
    out = state.sample_lookup.lookup(state.sample_reads, atlas.on_surface(x), state.cfg.lookup_k)
    return out.to(x.dtype)


def _painted(state: EditState, probs: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Painted colour and mask [M, 4] (rgb, mask) from chart probabilities [M, n] and coordinates [M, n, 2]."""
    return blend_charts(state.edit_textures, uv, probs)


def _filtered_lookup(state: EditState, tr: Trace, sel: torch.Tensor, xc: torch.Tensor, height: int, width: int,
                     focal: float, sub: int, texture_fn=None, threshold: bool = False,
                     crop: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Painted colour and mask of the rays `sel` [S] from sub x sub lookups per pixel, Blackman-Harris filtered in
    linear light (core/images/filter.py). xc [S, 3] canonical points. Returns (rgb [S, 3], mask [S]).
    threshold: apply the threshold blend's rule to each sub-pixel lookup before filtering (the mask becomes the
    filtered share of sub-pixels that pass it, the colour their filtered mean): blend the result softly.
    crop: work on the bounding box of the rays `sel` only (the same numbers: every pixel outside it is off the
    object, which the interpolation and the filter leave out anyway)."""
    dev = xc.device
    ray_depth = tr.depth[sel]
    if crop and sel.numel():
        rows, cols = sel // width, sel % width
        r0, c0 = int(rows.min()), int(cols.min())
        height, width = int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1
        sel = (rows - r0) * width + (cols - c0)  # the rays' pixels in the box
    n = height * width
    valid = torch.zeros(n, dtype=torch.bool, device=dev)
    valid[sel] = True
    canon = torch.zeros(n, 3, dtype=xc.dtype, device=dev)
    canon[sel] = xc
    depth = torch.zeros(n, dtype=xc.dtype, device=dev)
    depth[sel] = ray_depth
    # neighbours on the same surface: depth within 3 pixel footprints (an occlusion edge jumps much further)
    step = 3.0 * depth.abs() / focal_scale(focal)
    if texture_fn is None and state.sample_lookup is None:  # chart nets once per pixel, interpolated to sub-pixels
        probs, uv, on = subpixel_chart_uv(state.bundle.atlas, canon.view(height, width, 3), valid.view(height, width),
                                          depth.view(height, width), sub, step.view(height, width))
        looked = _painted(state, probs, uv)  # [K, 4]: rgb, mask
    else:  # a 3-D function, or the nearest samples' reads, at the sub-pixel points themselves
        sp = subpixel_points(canon.view(height, width, 3), valid.view(height, width), depth.view(height, width),
                             sub, step.view(height, width))
        on = torch.isfinite(sp).all(-1)
        looked = _lookup(state, sp[on], texture_fn)
    m = (looked[:, 3] > BLEND_THRESHOLD).to(xc.dtype) if threshold else looked[:, 3]
    vals = torch.zeros(4, *on.shape, dtype=xc.dtype, device=dev)
    vals[:3, on] = srgb_to_linear(looked[:, :3].clamp(0, 1)).T * (m if threshold else 1.0)
    vals[3, on] = m
    px = filter_down(vals, on, sub).reshape(4, n)[:, sel]
    if threshold:  # mean colour of the passing sub-pixels (any colour where none passes: its weight is 0)
        px[:3] = px[:3] / px[3:4].clamp_min(1e-6)
    return linear_to_srgb(px[:3].T.clamp(0, 1)), px[3]


def _grid_lookup(state: EditState, low: Trace, grid: StretchGrid, sel: torch.Tensor, height: int, width: int,
                 texture_fn=None, threshold: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Painted colour and mask of the output rays `sel` [S] of an H x W frame traced on a squash grid: the texture
    looked up once per object ray of the grid's trace `low` and averaged back over each output pixel as the frame's
    colour is (`warp_frame`: the grid_filter tent across the squash, then bicubic), in linear light: the mask
    weighted by the grid rays on the object, the colour by their mask too (the soft blend m T + (1 − m) c of the
    averaged pair is then the average of each grid ray's blend over a pixel's colour c). threshold: the threshold
    blend's rule per grid ray before the average (as `_filtered_lookup`). Returns (rgb [S, 3], mask [S], ok [S]);
    ok False where grid rays on the object hold less than GRID_LOOKUP_MIN_WEIGHT of the pixel's filter (its values
    are then meaningless: look it up another way)."""
    dev, dtype = low.x.device, low.x.dtype
    lsel = torch.nonzero(low.active & (low.fg > 1e-4)).squeeze(1)
    vals = torch.zeros(grid.height * grid.width, 5, dtype=dtype, device=dev)
    if lsel.numel():
        xc = state.canonical_surface(low, lsel)
        xc = torch.where(torch.isfinite(xc).all(1, keepdim=True), xc, low.x[lsel].nan_to_num(0.0))
        looked = _lookup(state, xc, texture_fn)
        m = (looked[:, 3] > BLEND_THRESHOLD).to(dtype) if threshold else looked[:, 3].to(dtype)
        vals[lsel, :3] = srgb_to_linear(looked[:, :3].clamp(0, 1)).to(dtype) * m[:, None]
        vals[lsel, 3] = m
        vals[lsel, 4] = 1.0
    out = warp_frame(vals.view(grid.height, grid.width, 5), grid, height, width,
                     filter_pixels=float(state.cfg.grid_filter)).reshape(-1, 5)[sel].to(dtype)
    w = out[:, 4]
    ok = w > GRID_LOOKUP_MIN_WEIGHT
    m = out[:, 3] / w.clamp_min(GRID_LOOKUP_MIN_WEIGHT)
    lin = out[:, :3] / out[:, 3:4].clamp_min(1e-6)
    return linear_to_srgb(lin.clamp(0, 1)), m.clamp(0, 1), ok


def _trace(state: EditState, c2w: torch.Tensor, height: int, width: int, focal, soft: bool, scale: float,
           k: int | None = None) -> Trace:
    """The edited points traced for one frame (neighbours, attention, the occlusion rule's visible layer); soft:
    footprint windows at scale factor `scale` (the `footprint` modes beyond the training scale); k: neighbours per
    ray (None: the model's)."""
    model, cfg = state.bundle.model, state.cfg
    index = None if soft else state.search_index(c2w, height, width, focal, k)  # shared with the occlusion rule
    radius_scale, reach = state.search_radius()
    tr = trace_frame(model, c2w, height, width, focal, points=state.points, influence=state.influence, k=k,
                     temperature=cfg.temperature, inv_f=state.inv_f_attention_at if cfg.f_attention else None,
                     rebase_depth=state.rebase_depth,
                     radius_scale=radius_scale, reach=reach, attention=cfg.attention,
                     reach_gate=state.reach_gate, reach_surround=state.reach_surround,
                     reach_gate_own=state.reach_gate_own, reach_between=state.reach_between,
                     reach_perspective=state.reach_perspective,
                     soft_scale=scale if soft else 1.0, index=index)
    return state.visible_layer(tr, None if soft else c2w, None if soft else focal, index=index)


def _scales(state: EditState, c2w: torch.Tensor, focal) -> tuple[float, float]:
    """The frame's scale factor against the training footprint and the decoder's (`decoder_scale`); moved points
    in their own size (an object scaled by s has s times larger pixels)."""
    model = state.bundle.model
    if state.points is None:
        return (scale_factor(float(model.train_footprint), c2w, focal, model.xyz.detach()),
                decoder_scale(model, None, c2w, focal, model.xyz.detach()))
    pts, centre = state.points.detach(), state.centre
    return (scale_factor(float(model.train_footprint) * state.local_scale, c2w, focal, pts, centre),
            decoder_scale(model, None, c2w, focal, pts, size_scale=state.local_scale, centre=centre))


def _stretched(state: EditState, c2w: torch.Tensor, height: int, width: int, focal,
               dscale: float) -> StretchGrid | None:
    """The `StretchGrid` an `upsampled` frame of moved points is traced on, else None (the frame's one scale,
    dscale). A stretch: where that one scale traces a frame coarser than the output (dscale > 1) and the surface
    is stretched on the screen at least EditConfig.stretch_grid times more along one direction than across it, the
    grid has the one-scale frame's pixels (dscale² output pixels each), spent otherwise: across the stretch at the
    screen's own scale (camera × across, at least 1), along it the rest. A squash: where the frame is traced at
    the output's pixels (dscale ≤ 1) and the surface is squashed on the screen at least EditConfig.squash_grid
    times more across one direction than along it and to at most 1 / squash_grid of the training scale (camera ×
    across), the grid keeps the output's pixels along it and is finer across it, at the training scale (at most
    1 / EditConfig.squash_grid_finest times finer, and at most SQUASH_GRID_MAX_PIXELS times the output's pixels in
    all); `warp_frame` averages it back over each output pixel."""
    ratio = float(state.cfg.stretch_grid) if dscale > 1.0 else float(state.cfg.squash_grid)
    if not (state.moved and ratio > 0):
        return None
    key = (tuple(c2w.reshape(-1).tolist()), height, width, repr(focal))
    if state._grid is not None and state._grid[0] == key:  # render_edited asks again for the frame it traced
        return state._grid[1]
    grid = None
    along, across, angle = state.screen_stretch(c2w)
    if across > 0 and along >= ratio * across:
        # the camera's own scale factor against the decoder's pixel (the object's size left out)
        camera = scale_factor(decoder_footprint(state.bundle.model), c2w, focal, state.points.detach(), state.centre)
        if dscale > 1.0:  # a stretch: the one-scale frame's pixels, across it at the screen's own scale
            s_across = max(camera * across, 1.0)
            grid = stretch_grid(c2w, height, width, focal, (max(dscale * dscale / s_across, s_across), s_across),
                                angle, points=state.points)
        elif camera * across * ratio <= 1.0:  # a squash: the output's pixels along it, the training scale across
            s_across = max(camera * across, float(state.cfg.squash_grid_finest), MIN_GRID_SCALE)
            grid = stretch_grid(c2w, height, width, focal, (1.0, s_across), angle, points=state.points)
            budget = SQUASH_GRID_MAX_PIXELS * height * width
            if grid.height * grid.width > budget:  # a grid left whole (a point behind the camera) or a huge part
                s_across = min(s_across * grid.height * grid.width / budget, 1.0)
                grid = stretch_grid(c2w, height, width, focal, (1.0, s_across), angle, points=state.points)
    state._grid = (key, grid)
    return grid


def _low_frame(state: EditState, c2w: torch.Tensor, height: int, width: int, focal, parts: set,
               dscale: float):
    """The training-scale frame an `upsampled` frame is traced on: (c2w, h, w, focal, grid), grid the frame's
    `StretchGrid` (`_stretched`) or None (the same camera scaled, `low_size`); None when every ray is traced."""
    if "upsampled" not in parts:
        return None
    grid = _stretched(state, c2w, height, width, focal, dscale)
    if grid is not None:
        return grid.c2w, grid.height, grid.width, grid.focal, grid
    if dscale > 1.0:
        lh, lw, s = low_size(height, width, dscale)
        return c2w, lh, lw, scaled_focal(focal, s), None
    return None


def frame_trace(state: EditState, c2w: torch.Tensor, height: int, width: int, focal, k: int | None = None) -> Trace:
    """Neighbours and attention of one frame as `render_edited` traces it (pass the result back as its `trace`):
    in the `upsampled` mode beyond the training scale the training-scale frame is traced and the full-size trace
    interpolated from it (`interpolate_trace`, the training-scale trace kept as its `coarse`; a stretched frame's
    on its `StretchGrid`); otherwise every ray is traced. k: neighbours per ray (None: the model's)."""
    parts = set(check_mode(state.cfg.render_mode, state.bundle.model).split("+"))
    scale, dscale = _scales(state, c2w, focal)
    low_frame = _low_frame(state, c2w, height, width, focal, parts, dscale)
    if low_frame is not None:
        lc2w, lh, lw, low_focal, grid = low_frame
        low = _trace(state, lc2w, lh, lw, low_focal, False, 1.0, k)
        return interpolate_trace(low, c2w, height, width, focal, low_focal,
                                 coords=None if grid is None else grid.coords)
    return _trace(state, c2w, height, width, focal, "footprint" in parts and scale > 1.0, scale, k)


@torch.no_grad()
def render_edited(state: EditState, c2w: torch.Tensor, height: int, width: int, focal: float,
                  background=(1.0, 1.0, 1.0), trace: Trace | None = None, texture_fn=None) -> dict:
    """One frame: dict(rgb [H, W, 3] over `background`, alpha [H, W] (the coverage: decoder mask head, else 1 − bg),
    x_can [H, W, 3] (NaN off the object), stats, trace).

    trace: the 'trace' of an earlier render_edited call with the same points, camera and temperature (several
    texture edits or correspondence modes of one frame then share neighbours and attention).
    texture_fn(x_can [M, 3]) -> rgb [M, 3]: colour textured rays from this function instead of the painted atlas
    (same correspondence, filtering and coverage; with colour="atlas" every object ray)."""
    t0 = time.perf_counter()
    bundle, cfg = state.bundle, state.cfg
    model = bundle.model
    parts = set(check_mode(cfg.render_mode, model).split("+"))
    scale, dscale = _scales(state, c2w, focal)
    tr = frame_trace(state, c2w, height, width, focal) if trace is None else trace
    trace_seconds = 0.0 if trace is not None else time.perf_counter() - t0
    low_frame = _low_frame(state, c2w, height, width, focal, parts, dscale)
    squash = None  # (grid, its trace) where the texture is averaged on a squash grid (EditConfig.grid_texture)
    if low_frame is not None:  # the model's colour and coverage at the training scale, resampled to the frame
        lc2w, lh, lw, low_focal, grid = low_frame
        low = None if tr.coarse is None else tr.coarse.low
        if low is None or low.shape != (lh, lw):  # a caller's trace of every full-size ray
            low = _trace(state, lc2w, lh, lw, low_focal, False, 1.0)
        low_rgb, low_alpha = shade_frame(model, low, background, features=state.features, with_alpha=True)
        low_alpha = (1.0 - low.bg).reshape(lh, lw) if low_alpha is None else low_alpha

        def resample(img):  # bicubic: from the camera scaled, or from a StretchGrid (a squash's first filtered)
            if grid is None:
                return upsample_frame(img, height, width)
            return warp_frame(img, grid, height, width, filter_pixels=float(cfg.grid_filter))
        rgb, dec_alpha = resample(low_rgb), resample(low_alpha.clamp(0, 1))
        # a squash grid (finer than the output across it; a stretch grid's pixels are at least the output's)
        if grid is not None and grid.scales[1] < 1.0 and grid.scales[1] <= float(cfg.grid_texture):
            squash = grid, low
    else:
        rgb, dec_alpha = shade_frame(model, tr, background, features=state.features, with_alpha=True,
                                     decoder_scale=dscale if "decoder" in parts else 1.0,
                                     coverage_scale=dscale if "filtered" in parts else 1.0,
                                     interior_scale=dscale if "interior" in parts else 1.0)
    rgb = rgb.reshape(-1, 3)
    fg = tr.fg
    # Coverage of painted rays: the decoder's mask head when it has one (sharp silhouettes, opaque interior),
    # else the attention's foreground weight.
    cover = fg if dec_alpha is None else dec_alpha.reshape(-1)
    hit = tr.active & (fg > 1e-4)
    x_can = torch.full_like(tr.x, float("nan"))
    stats = {"rays": int(tr.idx.shape[0]), "rays_shaded": int(tr.active.sum()),
             "non_finite_points": state.non_finite_points, "filled_points": state.filled_points,
             "texture_rays": 0, "correspondence": "skipped",
             "trace_seconds": trace_seconds}
    if state.textured and bool(hit.any()):
        sel = torch.nonzero(hit).squeeze(1)
        x_hat = tr.x[sel]
        xc = state.canonical_surface(tr, sel)
        if state.moved:
            stats["correspondence"] = cfg.correspondence
        bad = ~torch.isfinite(xc).all(1)
        stats["non_finite_lookups_repaired"] = int(bad.sum())
        xc = torch.where(bad[:, None], x_hat.nan_to_num(0.0), xc)
        mode = cfg.blend
        if squash is not None:  # averaged over the grid like the colour; pixels the grid's object misses: one lookup
            tex, m, ok = _grid_lookup(state, squash[1], squash[0], sel, height, width, texture_fn,
                                      threshold=cfg.blend == "threshold")
            if not bool(ok.all()):
                looked = _lookup(state, xc[~ok], texture_fn)
                if cfg.blend == "threshold":
                    looked[:, 3] = (looked[:, 3] > BLEND_THRESHOLD).to(looked.dtype)
                tex[~ok], m[~ok] = looked[:, :3].to(tex.dtype), looked[:, 3].to(m.dtype)
            mode = "soft"
        elif cfg.antialias > 1:
            tex, m = _filtered_lookup(state, tr, sel, xc, height, width, focal, cfg.antialias, texture_fn,
                                      threshold=cfg.blend == "threshold")
            mode = "soft"  # a threshold was applied per sub-pixel, before the filter
        else:
            looked = _lookup(state, xc, texture_fn)
            tex, m = looked[:, :3], looked[:, 3]
        bgc = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device)
        f = cover[sel][:, None]
        # The point render is f·c + (1 − f)·background; edit the object colour c, keep the coverage f.
        c = ((rgb[sel] - (1 - f) * bgc) / f.clamp_min(1e-4)).clamp(0, 1)
        rgb[sel] = f * blend(c, tex, m, mode) + (1 - f) * bgc
        x_can[sel] = xc
        stats["texture_rays"] = int(sel.numel())
    stats["reshaded_rays"] = _reshade(state, tr, rgb, cover, hit, background)
    rgb = torch.nan_to_num(rgb, nan=1.0).clamp(0, 1).reshape(height, width, 3)
    cover = cover.clamp(0, 1).reshape(height, width)
    if "filtered" in parts and scale > 1.0:  # no point discs beyond the training resolution
        sigma = filter_sigma(scale)
        rgb, cover = gaussian_blur(rgb, sigma).clamp(0, 1), gaussian_blur(cover, sigma).clamp(0, 1)
    stats["seconds"] = time.perf_counter() - t0
    stats["scale"] = scale
    grid = None if low_frame is None else low_frame[4]
    stats["grid"] = None if grid is None else [float(v) for v in grid.scales]  # (along, across), or None
    stats["grid_texture"] = squash is not None
    return {"rgb": rgb, "alpha": cover,
            "x_can": x_can.reshape(height, width, 3), "stats": stats, "trace": tr}


def _reshade(state: EditState, tr: Trace, rgb: torch.Tensor, cover: torch.Tensor, hit: torch.Tensor,
             background) -> int:
    """EditConfig.reshade: `reshade_rays` on the rays hit [R] with the shading fitted to the model's atlas
    (core/edits/shading.py `atlas_shading`). Returns the rays re-shaded (0: the points did not move, the setting is
    off, or auto found no shading)."""
    mode = state.cfg.reshade
    if mode == "off" or not state.moved or not bool(hit.any()):
        return 0
    shading = atlas_shading(state.bundle)
    if shading is None or (mode == "auto" and shading.log_range < RESHADE_MIN_RANGE):
        return 0
    sel = torch.nonzero(hit).squeeze(1)
    reshade_rays(state, tr, rgb, cover, sel, shading.b, background)
    return int(sel.numel())


def reshade_rays(state: EditState, tr: Trace, rgb: torch.Tensor, cover: torch.Tensor, sel: torch.Tensor,
                 b: torch.Tensor, background=(1.0, 1.0, 1.0)) -> None:
    """Multiply the object colour of the rays sel [S] long of a frame traced from `state`'s moved points (rgb [R, 3]
    over `background` with coverage cover [R], changed in place; any float dtype) by S(posed normal) / S(rest
    normal) in linear light, S = exp(b · sh_basis(n)) with b [8], each ray by its most-attended neighbour's F and
    canonical normal (core/edits/shading.py `reshade_factor`)."""
    near = tr.idx[sel].gather(1, tr.weights[sel].argmax(1, keepdim=True)).squeeze(1).clamp_min(0)
    cid = near if state.ids is None else state.ids[near]
    normals = field_for(state.bundle.model, state.deformation_cfg).normals().to(rgb.device)
    ratio = reshade_factor(state.f[near], normals[cid], tr.dirs.reshape(-1, 3)[sel], b).to(rgb.dtype)
    bgc = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device)
    f = cover[sel].clamp(1e-4, 1.0)[:, None]
    c = ((rgb[sel] - (1 - f) * bgc) / f).clamp(0, 1)
    rgb[sel] = f * linear_to_srgb((srgb_to_linear(c) * ratio[:, None]).clamp(0, 1)) + (1 - f) * bgc


def warm_up(bundle, cfg: EditConfig | None = None, size: int = 16) -> float:
    """Render tiny deformed frames of `bundle` (size × size pixels, a camera that sees every point) with `cfg`
    (default: EditConfig()), and with every object ray coloured through the atlas when the bundle has one, and
    throw them away; returns their seconds. The first deformed or textured frame of a process pays for one-off
    work (numba compiling or loading the deformation, neighbour, attention and chart-piece loops, the model's
    canonical neighbourhoods): a caller that times frames, or must answer at once, runs this first. The points
    move by a thousandth of a spacing, so the deformation path runs without changing anything the bundle caches
    per pose."""
    cfg = cfg or EditConfig()
    t0 = time.perf_counter()
    with torch.no_grad():
        xyz = bundle.model.xyz.detach()
        centre = xyz.mean(0)
        radius = float((xyz - centre).norm(dim=1).max().clamp_min(1e-6))
        eye = tuple(float(v) for v in centre + torch.tensor([0.0, -2.5, 1.5], device=xyz.device) * radius)
        c2w = look_at(eye, target=tuple(float(v) for v in centre)).float().to(xyz.device)
        moved = xyz + 1e-3 * float(bundle.model.spacing)
        cfgs = [cfg] + ([dataclasses.replace(cfg, colour="atlas")]
                        if bundle.atlas is not None and cfg.colour != "atlas" else [])
        for c in cfgs:
            render_edited(EditState(bundle, points=moved, cfg=c), c2w, size, size, focal_from_fov(size, 0.69))
    return time.perf_counter() - t0
