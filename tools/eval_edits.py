"""Ground-truth evaluation of simultaneous geometry + texture edits (needs bpy; `pointgt eval-edits`).

For each rig pose of a built-in scene at increasing magnitudes:
  ground truth  the posed mesh rendered by Cycles (`tools.scenes.build.render_variant`, cached in the scene dir),
                with the base texture, a global procedural retexture, or the scene's decal over the base texture;
  ours          the model's canonical points deformed by the SAME rig (a vertex-only mesh in the scene.blend with
                `tools.scenes.poses.apply_pose`, evaluated positions read with foreach_get), rendered by
                `core.frames.edited.render_edited` with the procedural texture baked into the atlas.
Every edit is scored for each correspondence (the paper's naive and deformation-aware, and deform-gradient), at
each attention temperature and with each renderer variant (`RENDERERS`: today's, or with the local deformation
gradients in the attention keys and/or the neighbour radius); the decal also with the soft and the threshold blend. Attention diagnostics explain the correspondence figures: the two
correspondences differ, ray by ray, by exactly the offset of the surface point x̂ from its ray (see `diagnostics`).
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from core.config import check_flag
from core.edits.bake import bake
from core.edits.correspondence import ray_canonical_points
from core.edits.deformation import MAX_STRETCH, DeformationConfig, field_for
from core.edits.procedural import evaluate, get_texture
from core.frames.edited import EditConfig, EditState, render_edited, warm_up
from core.images.metrics import blank_floor, mean_scores, object_mask, psnr, score_views
from core.images.rays import project_on_ray
from core.points.trace import Trace
from core.util.atomic import atomic_write_text
from core.util.errors import DataError, InputError

EDITS = ("geometry", "retexture", "decal")
# renderer variants: the EditConfig fields each sets (every F switch named: the defaults may change); "paper" =
# the paper's renderer, correspondence and atlas lookup (the chart networks at each point); the variants built on
# _AUTO (the default renderer's family) look up through the stored samples, the default. f_compression also
# changes the deform-gradient correspondence.
_PAPER = {"f_attention": False, "f_radius": False, "f_compression": "tangent", "f_fill": False, "fold_radius": 0.0,
          "f_depth": "ray",
          "f_occlusion": False, "f_fill_features": "nearer", "fold_test": "displacement", "f_radius_rule": "gap",
          "f_reach_gate": 0.0, "f_key_stretch": "full", "f_reach_surround": False, "f_reach_gate_own": False,
          "f_reach_between": False, "f_fill_tear": MAX_STRETCH, "f_fill_budget": 1.0, "f_reach_perspective": 0.0,
          "stretch_grid": 0.0, "squash_grid": 0.0, "grid_texture": 0.0, "lookup": "charts",
          "f_correspondence_compression": "keys", "reshade": "off"}
# F-aware keys, blended fill, fold rule, canonical depths, compression by the model's thickness; with the budget reach
_AUTO = {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0, "f_fill_features": "blend",
         "f_depth": "nearest", "f_compression": "auto", "lookup": "samples"}
_BUDGET = {**_AUTO, "f_radius": True, "f_radius_rule": "budget"}
# the budget reach gated at 1.5 caps between points, the keys' stretch capped at the fill's gap
_BETWEEN_GAP = {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "gap"}
# the keys' stretch by the model's thickness and the perspective reach; with the stretch grid, the squash grid, the
# perspective reach's factor at 16, and the texture averaged on the squash grid (with the occlusion rule: the default
# renderer, `-tex-occ`)
_PERSP = {**_BETWEEN_GAP, "f_key_stretch": "auto", "f_reach_perspective": 4.0}
_GRID = {**_PERSP, "stretch_grid": 1.5}
_SQUASH = {**_GRID, "squash_grid": 1.5}
_SQUASH16 = {**_SQUASH, "f_reach_perspective": 16.0}
_SQUASH_TEX = {**_SQUASH16, "grid_texture": 0.25}
RENDERERS = {"paper": _PAPER, "f-attention": {**_PAPER, "f_attention": True},
             "f-radius": {**_PAPER, "f_radius": True, "f_radius_rule": "frame"},
             "f-both": {**_PAPER, "f_attention": True, "f_radius": True, "f_radius_rule": "frame"},
             "f-keep": {**_PAPER, "f_attention": True, "f_compression": "keep"},
             "f-squash": {**_PAPER, "f_attention": True, "f_compression": "undo"},
             "fill": {**_PAPER, "f_fill": True}, "f-fill": {**_PAPER, "f_attention": True, "f_fill": True},
             "fold": {**_PAPER, "fold_radius": 2.0}, "fill-fold": {**_PAPER, "f_fill": True, "fold_radius": 2.0},
             "f-fold": {**_PAPER, "f_attention": True, "fold_radius": 2.0},
             "f-fill-fold": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0},
             "f-fill-fold-occ": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0, "f_occlusion": True},
             "f-fill-fold-blend": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0,
                                   "f_fill_features": "blend"},
             "f-fill-fold-local": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 0.5,
                                   "fold_test": "local-map"},
             "f-fill-fold-blend-local": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 0.5,
                                         "fold_test": "local-map", "f_fill_features": "blend"},
             "f-fill-fold-blend-reach": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0,
                                         "f_fill_features": "blend", "f_radius": True},
             "f-fill-fold-blend-undo": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0,
                                        "f_fill_features": "blend", "f_compression": "undo"},
             "f-fill-fold-blend-depth": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0,
                                         "f_fill_features": "blend", "f_depth": "nearest"},
             "f-fill-fold-blend-depth-undo": {**_PAPER, "f_attention": True, "f_fill": True, "fold_radius": 2.0,
                                              "f_fill_features": "blend", "f_depth": "nearest",
                                              "f_compression": "undo"},
             "f-fill-fold-blend-depth-auto": _AUTO,
             "f-fill-fold-blend-depth-auto-reach": {**_AUTO, "f_radius": True},
             "f-fill-fold-blend-depth-auto-budget": _BUDGET,
             "f-fill-fold-blend-depth-auto-budget-gate": {**_BUDGET, "f_reach_gate": 1.0},
             "f-fill-fold-blend-depth-auto-budget-gate2": {**_BUDGET, "f_reach_gate": 2.0},
             "f-fill-fold-blend-depth-auto-gap": {**_AUTO, "f_key_stretch": "gap"},
             "f-fill-fold-blend-depth-auto-gap-occ": {**_AUTO, "f_key_stretch": "gap", "f_occlusion": True},
             "f-fill-fold-blend-depth-auto-budget-gate-gap": {**_BUDGET, "f_reach_gate": 1.0, "f_key_stretch": "gap"},
             "f-fill-fold-blend-depth-auto-budget-surround": {**_BUDGET, "f_reach_gate": 1.0,
                                                             "f_reach_surround": True},
             "f-fill-fold-blend-depth-auto-budget-gate15": {**_BUDGET, "f_reach_gate": 1.5},
             "f-fill-fold-blend-depth-auto-budget-gate15-own": {**_BUDGET, "f_reach_gate": 1.5,
                                                               "f_reach_gate_own": True},
             "f-fill-fold-blend-depth-auto-budget-between": {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True},
             "f-fill-fold-blend-depth-auto-budget-between2": {**_BUDGET, "f_reach_gate": 2.0, "f_reach_between": True},
             "f-fill-fold-blend-depth-auto-budget-between-gap": _BETWEEN_GAP,
             "f-fill-fold-blend-depth-auto-budget-between-gap-occ": {**_BETWEEN_GAP, "f_occlusion": True},
             "f-fill-fold-blend-depth-auto-budget-between-sparse": {**_BETWEEN_GAP, "f_key_stretch": "sparse"},
             "f-fill-fold-blend-depth-auto-budget-between-auto": {**_BETWEEN_GAP, "f_key_stretch": "auto"},
             "f-fill-fold-blend-depth-auto-budget-between-auto-occ": {**_BETWEEN_GAP, "f_key_stretch": "auto",
                                                                     "f_occlusion": True},
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp": _PERSP,
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp-grid": _GRID,
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp-grid-occ": {**_GRID, "f_occlusion": True},
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp-grid-squash": _SQUASH,
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp-grid-squash-occ": {**_SQUASH, "f_occlusion": True},
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp16-grid-squash": _SQUASH16,
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp16-grid-squash-occ": {**_SQUASH16,
                                                                                         "f_occlusion": True},
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp16-grid-squash-tex": _SQUASH_TEX,
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp16-grid-squash-tex-occ": {**_SQUASH_TEX,
                                                                                             "f_occlusion": True},
             # the deform-gradient correspondence undoing no compression (rotation and stretch only)
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp16-grid-squash-tex-occ-ckeep": {
                 **_SQUASH_TEX, "f_occlusion": True, "f_correspondence_compression": "keep"},
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp16-grid-squash-texall": {**_SQUASH16,
                                                                                            "grid_texture": 1.0},
             "f-fill-fold-blend-depth-auto-budget-between-auto-persp-pixels": {**_PERSP, "render_mode": "pixels"},
             "f-fill-fold-blend-depth-auto-budget-between-auto-keep": {**_BETWEEN_GAP, "f_key_stretch": "auto",
                                                                      "f_compression": "keep"},
             "f-fill-fold-blend-depth-auto-budget-between-sparse-occ": {**_BETWEEN_GAP, "f_key_stretch": "sparse",
                                                                       "f_occlusion": True},
             "f-fill-fold-blend-depth-auto-budget-between-gap-tear": {**_BETWEEN_GAP, "f_fill_tear": 13.5},
             "f-fill-fold-blend-depth-auto-budget-between-gap-b2": {**_BETWEEN_GAP, "f_fill_budget": 2.0},
             "f-fill-fold-blend-depth-auto-budget-between-gap-b3": {**_BETWEEN_GAP, "f_fill_budget": 3.0},
             "f-fill-fold-blend-depth-auto-budget-between-gap-pixels": {**_BETWEEN_GAP, "render_mode": "pixels"},
             "f-fill-fold-blend-depth-auto-budget-gate15-gap-b3": {**_BUDGET, "f_reach_gate": 1.5,
                                                                   "f_key_stretch": "gap", "f_fill_budget": 3.0},
             "f-fill-fold-blend-depth-auto-budget-between25-gap-b2": {**_BUDGET, "f_reach_gate": 2.5,
                                                                      "f_reach_between": True, "f_key_stretch": "gap",
                                                                      "f_fill_budget": 2.0},
             "f-fill-fold-blend-depth-auto-budget-gate15-gap": {**_BUDGET, "f_reach_gate": 1.5, "f_key_stretch": "gap"},
             "f-fill-fold-blend-depth-auto-budget-gate15-gap-b2": {**_BUDGET, "f_reach_gate": 1.5,
                                                                   "f_key_stretch": "gap", "f_fill_budget": 2.0},
             "f-fill-fold-blend-depth-auto-budget-between25-gap-b3": {**_BUDGET, "f_reach_gate": 2.5,
                                                                      "f_reach_between": True, "f_key_stretch": "gap",
                                                                      "f_fill_budget": 3.0}}
CORRESPONDENCES = ("naive", "deform-aware", "deform-gradient")


def describe_renderer(name: str) -> str:
    """A renderer variant in words: the EditConfig switches it sets beyond the paper's renderer (`pointgt render
    --help` says what each does)."""
    changed = [f"{k} {v}" for k, v in RENDERERS[name].items() if _PAPER.get(k) != v]
    return ", ".join(changed) if changed else "the paper's renderer, correspondence and atlas lookup"


def renderers_help() -> str:
    """Every renderer variant with its switches, for --renderers' help and the report's legend."""
    return " | ".join(f"{n} ({describe_renderer(n)})" for n in RENDERERS)


def default_renderer() -> str:
    """The RENDERERS key whose fields are all EditConfig's defaults (what `pointgt render` does by default)."""
    return next(k for k, v in RENDERERS.items() if all(getattr(EditConfig, f) == x for f, x in v.items()))


def compared_renderers() -> tuple[str, ...]:
    """The renderers eval-edits, the demo and the regions bench compare by default: the paper's and the default one
    (once, should they be the same)."""
    return tuple(dict.fromkeys(("paper", default_renderer())))


GT_TEXTURE = {"geometry": None, "retexture": "retexture", "decal": "decal"}  # "retexture" = the chosen texture
REST = ("rest", 0.0)


@dataclass(frozen=True)
class Method:
    """One way of rendering an edit: which edit, correspondence, attention temperature and texture blend."""

    edit: str
    correspondence: str  # see CORRESPONDENCES ("-" for the geometry-only edit: no texture lookup)
    temperature: float
    blend: str = "soft"
    renderer: str = "paper"  # a key of RENDERERS

    @property
    def label(self) -> str:
        return f"{self.renderer} {self.edit} {self.correspondence} T={self.temperature:g} {self.blend}"


def methods(temperatures=(1.0, 0.5), renderers=("paper",), correspondences=("naive", "deform-aware")) -> list[Method]:
    """Per renderer: geometry only per temperature; retexture and decal per correspondence and temperature (soft
    blend); the decal also with the threshold blend at the first temperature."""
    out = []
    for rd in renderers:
        for t in temperatures:
            out.append(Method("geometry", "-", t, renderer=rd))
            for edit in ("retexture", "decal"):
                for corr in correspondences:
                    out.append(Method(edit, corr, t, renderer=rd))
        for corr in correspondences:
            out.append(Method("decal", corr, temperatures[0], "threshold", renderer=rd))
    return out


def parse_floats(text: str, what: str) -> list[float]:
    try:
        vals = [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError as exc:
        raise InputError(f"{what}: expected comma-separated numbers, got {text!r}") from exc
    if not vals or not all(math.isfinite(v) for v in vals):
        raise InputError(f"{what}: expected finite comma-separated numbers, got {text!r}")
    return vals


# --- ground truth (Blender) -----------------------------------------------------------------------------------

def view_subset_dir(scene_dir: Path, views: int) -> Path:
    """A scene dir whose test cameras are `views` evenly spaced ones of the scene's (so Cycles renders only
    those): scene_dir itself when all are wanted, else scene_dir/eval_views<N>/ with links to the scene."""
    test_json = scene_dir / "transforms_test.json"
    if not test_json.exists():
        raise DataError(f"{test_json}: missing; create the scene with `pointgt make-scene NAME --out {scene_dir}`")
    doc = json.loads(test_json.read_text())
    frames = doc.get("frames") or []
    if views < 1:
        raise InputError(f"--views must be at least 1, got {views}")
    if views >= len(frames):
        return scene_dir
    pick = np.linspace(0, len(frames) - 1, views).round().astype(int)
    sub, _ = linked_scene_dir(scene_dir, f"eval_views{views}", {**doc, "frames": [frames[i] for i in pick]})
    return sub


def linked_scene_dir(scene_dir: Path, name: str, test_doc: dict) -> tuple[Path, bool]:
    """scene_dir/name/: a scene folder with links to scene_dir's blend file and spec and `test_doc` as its
    transforms_test.json (written when it differs), so Cycles renders those test cameras of the same scene. Returns
    (the folder, whether its test cameras were written)."""
    sub = scene_dir / name
    sub.mkdir(exist_ok=True)
    for fname in ("scene.blend", "scene.json"):
        link = sub / fname
        if not link.exists():
            link.symlink_to((scene_dir / fname).resolve())
    tj = sub / "transforms_test.json"
    changed = not tj.exists() or json.loads(tj.read_text()) != test_doc
    if changed:
        atomic_write_text(tj, json.dumps(test_doc, indent=1), backup=False)
    return sub, changed


def ground_truth(scene_dir: Path, pose: str, magnitude: float, texture: str | None, samples=None, log=print,
                 downscale: int = 1):
    """Cycles renders of the posed/retextured scene (cached): SplitData of the variant's test views, area-averaged
    by the integer factor downscale (the size of a model fitted with `pointgt fit --downscale`)."""
    from core.images.dataset import load_split
    from tools.scenes.build import render_variant, variant_dirname

    vdir = scene_dir / "poses" / variant_dirname(pose, magnitude if pose != "rest" else 1.0, texture)
    n_want = len(json.loads((scene_dir / "transforms_test.json").read_text())["frames"])
    cached = vdir / "variant.json"
    if cached.exists():
        meta = json.loads(cached.read_text())
        tj = vdir / "transforms_test.json"
        if (not tj.exists() or len(json.loads(tj.read_text())["frames"]) != n_want
                or meta.get("texture_params") != _texture_params(scene_dir, texture)):
            cached.unlink()  # stale: re-render
    if not cached.exists():
        t0 = time.perf_counter()
        render_variant(scene_dir, pose, magnitude if pose != "rest" else 1.0, texture, samples=samples,
                       log=lambda m: None)
        log(f"  ground truth {vdir.name}: {n_want} Cycles views in {time.perf_counter() - t0:.1f} s")
    return load_split(vdir, "test", downscale=downscale)


def _texture_params(scene_dir: Path, texture):
    from tools.scenes.spec import load_scene_spec

    return load_scene_spec(scene_dir)["texture"].get("params", {}).get(texture) if texture else None


def deform_points(points: np.ndarray, scene_dir: Path, pose: str, magnitude: float) -> np.ndarray:
    """The model's canonical points [N, 3] moved by the scene's rig for `pose` at `magnitude` -> [N, 3] float32.

    Opens scene.blend (so the rig is the very object the ground truth was rendered with), adds the points as a
    vertex-only mesh, gives it the pose's deformer with `apply_pose` and reads the evaluated positions.
    """
    import bpy

    from tools.scenes.poses import apply_pose
    from tools.scenes.render import open_scene

    spec, _ = open_scene(scene_dir)
    pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    me = bpy.data.meshes.new("pointgt_eval_points")
    me.vertices.add(len(pts))
    me.vertices.foreach_set("co", pts.ravel())
    me.update()
    obj = bpy.data.objects.new("pointgt_eval_points", me)
    bpy.context.scene.collection.objects.link(obj)
    apply_pose(obj, spec, pose, magnitude)
    deps = bpy.context.evaluated_depsgraph_get()
    deps.update()
    ev = obj.evaluated_get(deps)
    out = np.empty(len(ev.data.vertices) * 3, dtype=np.float32)
    if len(ev.data.vertices) != len(pts):
        raise DataError(f"rig '{pose}' changed the number of points ({len(pts)} -> {len(ev.data.vertices)})")
    ev.data.vertices.foreach_get("co", out)
    mw = np.array(obj.matrix_world, dtype=np.float32)
    out = out.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]
    return out


# --- ours ------------------------------------------------------------------------------------------------------

def edited_atlases(bundle, spec: dict, retexture: str, source: str = "auto") -> dict:
    """Packed atlas images [H, W, 3] per edit: the retexture baked everywhere, the decal over the fitted atlas
    (source: the bake's, core.edits.bake.bake)."""
    if bundle.atlas is None:
        raise InputError("this model has no atlas; run `pointgt atlas MODEL.pgt DATA` first")
    c, h = spec["bbox"]["center"], spec["bbox"]["half_size"]
    params = spec["texture"]["params"]
    retex = bake(bundle.atlas, lambda p: (evaluate(retexture, p, c, h, params.get(retexture))[0], None),
                 source=source)
    decal = bake(bundle.atlas, lambda p: evaluate("decal", p, c, h, params.get("decal")), source=source)
    return {"geometry": None, "retexture": retex, "decal": decal}


def diagnostics(out: dict, state: EditState) -> dict:
    """Attention sparsity and the correspondence gap on the object's rays (foreground weight > 0.5).

    max_weight: mean of the largest attention weight (1 = one point decides the ray);
    ray_dist: mean distance of x̂ = Σ a p_def from its ray, world units and in point spacings;
    corr_gap: mean |x_can(naive) − x_can(deform-aware)|. Algebraically naive − aware = x̂ − Π_ray(x̂), so
    corr_gap equals ray_dist: the correspondences differ only as far as x̂ is off its ray.
    """
    tr = out["trace"]
    hit = tr.active & (tr.fg > 0.5)
    if not bool(hit.any()):
        return {"rays_object": 0, "max_weight": float("nan"), "ray_dist": float("nan"),
                "ray_dist_spacings": float("nan"), "corr_gap": float("nan")}
    x = tr.x[hit]
    off = (x - project_on_ray(x, tr.origins[hit], tr.dirs[hit])).norm(dim=-1)
    spacing = float(state.bundle.model.spacing)
    naive = ray_canonical_points(tr, hit, state.points, state.p_can, "naive")
    aware = ray_canonical_points(tr, hit, state.points, state.p_can, "deform-aware")
    return {"rays_object": int(hit.sum()), "max_weight": float(tr.fg_weights[hit].max(dim=1).values.mean()),
            "ray_dist": float(off.mean()), "ray_dist_spacings": float(off.mean()) / max(spacing, 1e-12),
            "corr_gap": float((naive - aware).norm(dim=-1).mean())}


def oracle_retexture(state: EditState, view: tuple, trace: Trace, texture: str, spec: dict,
                     background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """The frame with the global texture evaluated exactly at the canonical points (no atlas), rendered like the
    atlas is — same correspondence, pixel filter and coverage: what the correspondence alone would give with a
    perfect atlas. view = (c2w, height, width, focal); trace: the edited frame's. rgb [H, W, 3]."""
    box, params = spec["bbox"], spec["texture"]["params"].get(texture)
    # state's points already hold any filled ones: take them, their canonical points and F as they are
    perfect = EditState(state.bundle, points=state.points if state.moved else None, ids=state.ids,
                        cfg=replace(state.cfg, colour="atlas", f_fill=False))
    perfect.p_can, perfect._f = state.p_can, state._f
    out = render_edited(perfect, *view, background, trace=trace,
                        texture_fn=lambda x: evaluate(texture, x, box["center"], box["half_size"], params)[0])
    return out["rgb"]


# EditConfig fields applied after the trace (neighbours + attention), so frames that differ only in them share it
TRACE_FREE_FIELDS = frozenset({"correspondence", "fold_radius", "fold_test", "blend", "mask_threshold", "colour",
                               "antialias", "grid_texture", "f_correspondence_compression"})


def score_frames(state: EditState, gt, background=(1.0, 1.0, 1.0), oracle: tuple | None = None,
                 traces: dict | None = None) -> dict:
    """Render every ground-truth view with `state`; mean PSNR (full, object), SSIM, seconds and diagnostics.
    oracle = (texture, scene spec): also score the texture evaluated exactly at x_can (psnr*_oracle), and the
    frame against that perfect-atlas frame on the object (psnr_object_vs_oracle: the atlas's error alone; the gap
    psnr_object_oracle − psnr_object in dB also depends on how well geometry and coverage match Blender).
    traces: a dict shared by the methods of one pose: neighbours + attention of a (view, temperature) are computed
    once; the reported seconds still include the time that trace took, so every row is a whole frame's cost."""
    # F is fitted once per state (these views share one pose); an animation fits it once per frame, so every
    # frame is charged the fit's time
    f_used = state.moved and (state.cfg.f_attention or state.cfg.f_radius or state.cfg.f_fill or
                              state.cfg.correspondence == "deform-gradient")
    f_seconds = 0.0
    if f_used:  # what the frame needs of F, before the timed frames
        if state.cfg.f_attention:
            _ = state.inv_f_attention
        if state.cfg.correspondence == "deform-gradient" or (state.cfg.fold_radius > 0
                                                             and state.cfg.fold_test == "local-map"):
            _ = state.inv_f_keys
        if state.cfg.f_radius:
            _ = state.search_radius()
        f_seconds = state.deformation_seconds

    def render(i):
        # what the trace (neighbours + attention) depends on: every EditConfig field but the ones applied after it,
        # so a field added later is in the key unless it is listed here as trace-free
        key = (i,) + tuple((f.name, getattr(state.cfg, f.name)) for f in dataclasses.fields(state.cfg)
                           if f.name not in TRACE_FREE_FIELDS)
        cached = traces.get(key) if traces is not None else None
        view = (gt.c2w[i], gt.height, gt.width, gt.focal)
        out = render_edited(state, *view, background, trace=cached[0] if cached else None)
        seconds = out["stats"]["seconds"] + f_seconds
        if cached:
            seconds += cached[1]
        elif traces is not None:
            traces[key] = (out["trace"], out["stats"]["trace_seconds"])
        st = out["stats"]
        out["extra"] = {"seconds": seconds, "texture_rays": st["texture_rays"],
                        "repaired": st.get("non_finite_lookups_repaired", 0), "grid": st.get("grid"),
                        **diagnostics(out, state)}
        if oracle is not None:
            perfect = oracle_retexture(state, view, out["trace"], *oracle, background=background)
            out["also"] = {"{}_oracle": perfect}
            # the atlas's own error: the frame against the perfect-atlas frame on the same object pixels (both
            # share geometry and coverage, whose error against Blender would otherwise set the floor of the gap)
            m = object_mask(gt.alphas[i].to(out["rgb"].device), out["alpha"])
            out["extra"]["psnr_object_vs_oracle"] = psnr(out["rgb"], perfect.to(out["rgb"].device), m)
        return out
    rows = score_views(render, gt.images, gt.alphas)
    keys = ("psnr", "psnr_object", "ssim", "seconds", "max_weight", "ray_dist", "ray_dist_spacings", "corr_gap")
    keys += ("psnr_oracle", "psnr_object_oracle", "psnr_object_vs_oracle") if oracle is not None else ()
    res = mean_scores(rows, keys)
    res["seconds_per_frame"] = res.pop("seconds")
    res["texture_rays"] = int(sum(r["texture_rays"] for r in rows))
    res["non_finite_lookups_repaired"] = int(sum(r["repaired"] for r in rows))
    res["grids"] = [r["grid"] for r in rows]  # per view: the StretchGrid's (along, across) scales, or None
    res["non_finite_points"] = state.non_finite_points
    return res


def blank_scores(gt) -> dict:
    """The floor: a blank white frame against the ground truth (full frame and on the object's pixels)."""
    return blank_floor(gt.images, gt.alphas)


# --- the whole evaluation ---------------------------------------------------------------------------------------

def run_eval(model_path, scene_dir, poses=None, magnitudes=(0.25, 0.5, 1.0), views: int = 4,
             temperatures=(1.0, 0.5), retexture: str = "stripes", samples=None, device: str = "cpu",
             antialias: int = EditConfig.antialias, renderers=("paper",), correspondences=("naive", "deform-aware"),
             log=print, lookup: str | None = None, bake_source: str = "auto", downscale: int = 1) -> dict:
    """Evaluate a model's edits against Blender ground truth; returns the JSON-able result (see module doc).
    lookup: every renderer's atlas lookup (EditConfig lookup; None: each renderer's own); bake_source: the
    retexture's and the decal's bake (core.edits.bake.bake source); downscale: the integer factor the ground truth
    is area-averaged by (a model fitted with `pointgt fit --downscale N` is scored at its training size with N)."""
    from core.bundle import load_bundle
    from tools.scenes.spec import load_scene_spec

    check_flag(downscale, "--downscale", min=1, max=64)
    scene_dir = Path(scene_dir)
    spec = load_scene_spec(scene_dir)
    tex = get_texture(retexture)
    if tex.local:
        raise InputError(f"--retexture {retexture}: that is a local decal; choose a global texture "
                         "(e.g. checker, stripes)")
    all_poses = [p for p in spec.get("poses", {}) if spec["poses"][p]["type"] != "rest"]
    poses = all_poses if not poses else list(poses)
    for p in poses:
        if p not in all_poses:
            raise InputError(f"unknown pose '{p}' for scene '{spec.get('name')}' ({scene_dir / 'scene.json'}); "
                             f"choose from {', '.join(all_poses)}")
    if not magnitudes or any(not math.isfinite(m) for m in magnitudes):
        raise InputError(f"--magnitudes must be finite numbers, got {magnitudes}")
    for rd in renderers:
        if rd not in RENDERERS:
            raise InputError(f"--renderers: unknown renderer '{rd}'; choose from {', '.join(RENDERERS)}")
    for c in correspondences:
        if c not in CORRESPONDENCES:
            raise InputError(f"--correspondences: unknown correspondence '{c}'; choose from {', '.join(CORRESPONDENCES)}")
    bundle = load_bundle(model_path, device=device)
    atlases = edited_atlases(bundle, spec, retexture, source=bake_source)
    gt_dir = view_subset_dir(scene_dir, views)
    plan = [REST] + [(p, float(m)) for p in poses for m in magnitudes]
    meths = methods(tuple(temperatures), tuple(renderers), tuple(correspondences))
    canonical = bundle.model.xyz.detach().cpu().numpy()
    rows, blanks = [], []
    def method_config(mt) -> EditConfig:
        over = RENDERERS[mt.renderer] if lookup is None else {**RENDERERS[mt.renderer], "lookup": lookup}
        return EditConfig(correspondence=mt.correspondence if mt.correspondence != "-" else "deform-aware",
                          blend=mt.blend, temperature=mt.temperature, antialias=antialias, **over)

    if len(plan) > 1:  # one-off work (compiling the deformation loops) must not land in the first pose's s/frame
        cfgs = {}  # one per renderer and correspondence (blend and temperature change nothing one-off)
        for mt in meths:
            cfg = method_config(mt)
            cfgs.setdefault((mt.renderer, cfg.correspondence), cfg)
        seconds = sum(warm_up(bundle, cfg) for _, cfg in sorted(cfgs.items(), key=lambda kv: kv[0]))
        log(f"warm-up (tiny deformed frames of each renderer and correspondence, not timed below): {seconds:.1f} s")
    t_start = time.perf_counter()
    for k, (pose, mag) in enumerate(plan):
        gts = {edit: ground_truth(gt_dir, pose, mag, retexture if edit == "retexture" else GT_TEXTURE[edit],
                                  samples, log, downscale=downscale) for edit in EDITS}
        for edit, gt in gts.items():
            blanks.append({"pose": pose, "magnitude": mag, "edit": edit, **blank_scores(gt)})
        points = None if pose == "rest" else deform_points(canonical, scene_dir, pose, mag)
        traces: dict = {}  # neighbours + attention per (view, temperature, renderer), shared by this pose's methods
        f_time: dict = {}  # one F fit per pose: its time is charged to every frame that uses F
        for mt in meths:
            state = EditState(bundle, points=points, atlas=atlases[mt.edit], cfg=method_config(mt))
            if "state" in f_time:  # reuse this pose's fit (same points): F and its measured time
                state.share_deformation(f_time["state"])
            res = score_frames(state, gts[mt.edit], oracle=(retexture, spec) if mt.edit == "retexture" else None,
                               traces=traces)
            if state._f is not None and "state" not in f_time:
                f_time["state"] = state
            rows.append({"pose": pose, "magnitude": mag, **asdict(mt), **res})
        log(f"[{k + 1}/{len(plan)}] {pose} m={mag:g}: " + "  ".join(
            f"{r['renderer']}/{r['edit'][:4]}/{r['correspondence']}/T{r['temperature']:g}/{r['blend'][:4]} "
            f"{r['psnr_object']:.2f}"
            for r in rows[-len(meths):]) + f"  ({time.perf_counter() - t_start:.0f} s)")
    result = {"model": str(model_path), "scene": str(scene_dir), "scene_name": spec.get("name"),
              "views": len(gts["geometry"]), "width": gts["geometry"].width, "height": gts["geometry"].height,
              "model_points": bundle.model.num_points, "point_spacing": float(bundle.model.spacing),
              "median_spread": field_for(bundle.model, DeformationConfig()).median_spread,
              "retexture": retexture, "decal": spec["texture"]["params"].get("decal"),
              "poses": poses, "magnitudes": list(magnitudes), "temperatures": list(temperatures), "antialias": antialias,
              "renderers": list(renderers), "correspondences": list(correspondences),
              "seconds_total": time.perf_counter() - t_start, "rows": rows, "blank": blanks}
    result["retexture_gap"] = retexture_gaps(rows)
    result["blend_comparison"] = blend_comparison(rows)
    return result


def _select(rows, **kw):
    return [r for r in rows if all(r.get(k, "paper" if k == "renderer" else None) == v for k, v in kw.items())]


def _sel_key(rows, key):
    """Rows of one method: key = (edit, correspondence, temperature, blend, renderer)."""
    return _select(rows, edit=key[0], correspondence=key[1], temperature=key[2], blend=key[3], renderer=key[4])


def ablation_markdown(result: dict) -> str:
    """The renderer × correspondence ablation: object PSNR (dB) per pose, magnitude and renderer, one column per
    edit and correspondence (first temperature, soft blend), and the mean seconds per frame of the row."""
    rows = result["rows"]
    t0 = result.get("temperatures", [rows[0]["temperature"]] if rows else [1.0])[0]
    corrs = result.get("correspondences", ["naive", "deform-aware"])
    cols = [("geometry", "-")] + [(e, c) for e in ("retexture", "decal") for c in corrs]
    head = ["geometry"] + [f"{e} {c}" for e, c in cols[1:]]
    lines = ["| pose | m | renderer | " + " | ".join(head) + " | s/frame |",
             "|---|---|---|" + "---|" * len(cols) + "---|"]
    cases = list(dict.fromkeys((r["pose"], r["magnitude"]) for r in rows))
    for pose, mag in cases:
        for rd in result.get("renderers", ["paper"]):
            cells, secs = [], []
            for edit, corr in cols:
                sel = _select(rows, pose=pose, magnitude=mag, renderer=rd, edit=edit, correspondence=corr,
                              temperature=t0, blend="soft")
                cells.append(_f(sel[0]["psnr_object"]) if sel else "–")
                secs += [x["seconds_per_frame"] for x in sel]
            lines.append(f"| {pose} | {mag:g} | {rd} | " + " | ".join(cells) +
                         f" | {np.mean(secs) if secs else float('nan'):.3f} |")
    return "\n".join(lines) + "\n"


def retexture_gaps(rows: list[dict]) -> list[dict]:
    """Texture persistence: PSNR(retexture at rest) − PSNR(retexture in each pose), full frame and object."""
    out = []
    for r in _select(rows, edit="retexture"):
        if r["pose"] == "rest":
            continue
        rest = _select(rows, edit="retexture", pose="rest", correspondence=r["correspondence"],
                       temperature=r["temperature"], blend=r["blend"], renderer=r.get("renderer", "paper"))
        if rest:
            out.append({k: r.get(k, "paper") for k in ("pose", "magnitude", "renderer", "correspondence", "temperature")} |
                       {"gap_psnr": rest[0]["psnr"] - r["psnr"], "gap_psnr_object": rest[0]["psnr_object"] - r["psnr_object"],
                        "gap_psnr_object_oracle": rest[0]["psnr_object_oracle"] - r["psnr_object_oracle"]})
    return out


def blend_comparison(rows: list[dict]) -> dict:
    """Soft vs threshold blend for the decal, mean over the posed (non-rest) cases, per correspondence."""
    out = {}
    temps = sorted({r["temperature"] for r in _select(rows, edit="decal", blend="threshold")})
    for rd, corr in dict.fromkeys((r.get("renderer", "paper"), r["correspondence"])
                                  for r in _select(rows, edit="decal", blend="threshold")):
        for t in temps:
            vals = {}
            for b in ("soft", "threshold"):
                rs = [r for r in _select(rows, edit="decal", correspondence=corr, temperature=t, blend=b)
                      if r["pose"] != "rest" and r.get("renderer", "paper") == rd]
                if rs:
                    vals[b] = {k: float(np.mean([r[k] for r in rs])) for k in ("psnr", "psnr_object", "ssim")}
            if len(vals) == 2:
                vals["better"] = "soft" if vals["soft"]["psnr_object"] >= vals["threshold"]["psnr_object"] else "threshold"
                out[(f"{rd} " if rd != "paper" else "") + f"{corr} T={t:g}"] = vals
    return out


# --- report -----------------------------------------------------------------------------------------------------

def _f(v, nd=2):
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def markdown(result: dict) -> str:
    """The result as markdown tables: per-case figures, summary per method, persistence gaps, blends, floors."""
    rows = result["rows"]
    lines = [f"Scene `{result['scene_name']}`, {result['views']} views at {result['width']}x{result['height']}, "
             f"model {result['model_points']} points (spacing {result['point_spacing']:.4f}"
             + (f", median spread {result['median_spread']:.2f}: "
                f"{'a thick shell' if result['median_spread'] >= EditConfig.f_thick_spread else 'a sheet'}"
                if "median_spread" in result else "") + "), "
             f"retexture `{result['retexture']}`, total {result['seconds_total']:.0f} s.", ""]
    names = list(dict.fromkeys(r.get("renderer", "paper") for r in rows if r.get("renderer", "paper") in RENDERERS))
    legend = "; ".join(f"{n} = {describe_renderer(n)}" for n in names)
    lines += [f"**Ablation** (object PSNR, dB; renderers, by the EditConfig switches they set: {legend}; first "
              "temperature, soft blend; "
              "s/frame = mean over the row's renders)", "",
              ablation_markdown(result)]
    # summary: mean over poses per magnitude, per method
    mags = sorted({r["magnitude"] for r in rows if r["pose"] != "rest"})
    lines += ["**Object PSNR (dB), mean over poses, per magnitude** (rest = unposed; s/frame = mean render time)", "",
              "| renderer | edit | correspondence | T | blend | rest | " + " | ".join(f"m={m:g}" for m in mags)
              + " | s/frame |", "|---|---|---|---|---|---|" + "---|" * len(mags) + "---|"]
    seen = []
    for r in rows:
        key = (r["edit"], r["correspondence"], r["temperature"], r["blend"], r.get("renderer", "paper"))
        if key in seen:
            continue
        seen.append(key)
        sel = _sel_key(rows, key)
        rest = [x["psnr_object"] for x in sel if x["pose"] == "rest"]
        per = [np.mean([x["psnr_object"] for x in sel if x["magnitude"] == m and x["pose"] != "rest"]) for m in mags]
        secs = np.mean([x["seconds_per_frame"] for x in sel])
        lines.append(f"| {key[4]} | {key[0]} | {key[1]} | {key[2]:g} | {key[3]} | {_f(rest[0] if rest else None)} | "
                     + " | ".join(_f(float(v)) for v in per) + f" | {secs:.2f} |")
    lines += ["", "**Retexture with a perfect atlas** (oracle: the texture evaluated exactly at x_can, rendered like the atlas; object PSNR, "
              "dB): the correspondence alone, without atlas error", "",
              "| renderer | correspondence | T | rest | " + " | ".join(f"m={m:g}" for m in mags) + " |",
              "|---|---|---|---|" + "---|" * len(mags)]
    for key in [k for k in seen if k[0] == "retexture"]:
        sel = _sel_key(rows, key)
        rest = [x["psnr_object_oracle"] for x in sel if x["pose"] == "rest"]
        per = [np.mean([x["psnr_object_oracle"] for x in sel if x["magnitude"] == m and x["pose"] != "rest"])
               for m in mags]
        lines.append(f"| {key[4]} | {key[1]} | {key[2]:g} | {_f(rest[0] if rest else None)} | "
                     + " | ".join(_f(float(v)) for v in per) + " |")
    lines += ["", "**Blank white frame (the floor)**, mean over poses (full frame / object pixels, dB)", "",
              "| edit | rest | " + " | ".join(f"m={m:g}" for m in mags) + " |", "|---|---|" + "---|" * len(mags)]
    for edit in EDITS:
        b = _select(result["blank"], edit=edit)
        cells = []
        for m in [None] + mags:
            s = [x for x in b if (x["pose"] == "rest" if m is None else (x["magnitude"] == m and x["pose"] != "rest"))]
            cells.append(f"{np.mean([x['psnr'] for x in s]):.2f} / {np.mean([x['psnr_object'] for x in s]):.2f}")
        lines.append(f"| {edit} | " + " | ".join(cells) + " |")
    lines += ["", "**Every case** (PSNR full / object dB, SSIM, s/frame; attention: mean max weight, x̂ distance "
              "to its ray and |naive − aware| correspondence gap, both in world units; for the retexture, object PSNR "
              "with the texture evaluated exactly at x_can (oracle: a perfect atlas), and the frame against the oracle's "
              "frame on the object (the atlas's error alone))", "",
              "| pose | m | renderer | edit | corr. | T | blend | PSNR | obj PSNR | SSIM | s/frame | max w | ray dist "
              "| corr gap | oracle obj PSNR | vs oracle |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['pose']} | {r['magnitude']:g} | {r.get('renderer', 'paper')} | {r['edit']} | "
                     f"{r['correspondence']} | "
                     f"{r['temperature']:g} | {r['blend']} | {_f(r['psnr'])} | {_f(r['psnr_object'])} | "
                     f"{_f(r['ssim'], 4)} | {r['seconds_per_frame']:.2f} | {_f(r['max_weight'], 3)} | "
                     f"{_f(r['ray_dist'], 4)} | {_f(r['corr_gap'], 4)} | {_f(r.get('psnr_object_oracle'))} | "
                     f"{_f(r.get('psnr_object_vs_oracle'))} |")
    lines += ["", "**Texture persistence**: retexture gap = object PSNR at rest − object PSNR in the pose (dB; "
              "smaller is better; oracle = with a perfect atlas)", "",
              "| pose | m | renderer | correspondence | T | gap (object) | gap (full) | gap (object, oracle) |",
              "|---|---|---|---|---|---|---|---|"]
    for g in result["retexture_gap"]:
        lines.append(f"| {g['pose']} | {g['magnitude']:g} | {g.get('renderer', 'paper')} | {g['correspondence']} | "
                     f"{g['temperature']:g} | "
                     f"{_f(g['gap_psnr_object'])} | {_f(g['gap_psnr'])} | {_f(g['gap_psnr_object_oracle'])} |")
    lines += ["", "**Decal blend**: soft vs threshold, mean over the posed cases (object PSNR / full PSNR / SSIM)", "",
              "| correspondence | soft | threshold | better |", "|---|---|---|---|"]
    for key, v in result["blend_comparison"].items():
        lines.append(f"| {key} | {_f(v['soft']['psnr_object'])} / {_f(v['soft']['psnr'])} / {_f(v['soft']['ssim'], 4)} | "
                     f"{_f(v['threshold']['psnr_object'])} / {_f(v['threshold']['psnr'])} / "
                     f"{_f(v['threshold']['ssim'], 4)} | {v['better']} |")
    return "\n".join(lines) + "\n"
