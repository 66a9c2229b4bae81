"""Posed frames across the scene library: each pose's object-PSNR gap to rest, per renderer, on every scene.

    python -m tools.bench.edits_library --work DIR [--scenes cloth,tube,...] [--steps 1000 | --minutes 10]
        [--renderers paper,DEFAULT,...] [--poses bend,...] [--views 4] [--threads 1] [--json OUT] [--markdown OUT]
        [--fit-args=--view-dependent --tag vd]

Per scene, each step a separate process, exactly what a user runs, and each reused when its output exists:
`pointgt make-scene` and the default stage-1 fit (as `python -m tools.bench.scenes --no-pair` makes them:
DIR/NAME, DIR/NAME.default.pgt), `pointgt atlas` with its defaults (or `--atlas-args`), then `pointgt eval-edits`
at magnitude 1 (the default correspondence, temperature 1, the soft blend; DIR/NAME.edits.json). The table gives,
per scene and renderer, the rest frame's object PSNR and, over the posed frames, the worst pose and its gap to rest
for the geometry-only edit and for the retexture (issue #16's bar: every pose within 3 dB of rest), and the mean
seconds per frame. The model's quality sets the rest figure: a weak fit has less to lose, so compare renderers
within one run (same models), and budgets across runs. `--fit-args` adds `pointgt fit` flags to every stage-1 fit under
`--tag` (DIR/NAME.TAG.default.pgt, DIR/NAME.TAG.edits.json), as `tools.bench.scenes` does.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

EDITS = ("geometry", "retexture")


SIZE = 128  # the scenes' training size (tools.bench.scenes' default)


def gaps(result: dict, correspondence: str | None = None) -> list[dict]:
    """Per renderer of one eval-edits result (its --json): rest object PSNR and the worst posed gap per edit.

    Reads rows at magnitude 1 (rest: magnitude 0), `correspondence`'s for the retexture (default: the first the
    result lists, deform-aware for a result that lists none; geometry has none), temperature 1, soft blend.
    Returns [{renderer, seconds_per_frame, <edit>: {rest, worst_pose, gap, within}}] with within = the number of
    poses whose gap is at most 3 dB, out of `poses`."""
    correspondence = correspondence or result.get("correspondences", ["deform-aware"])[0]
    rows = [r for r in result["rows"] if r["blend"] == "soft" and r["temperature"] == 1.0
            and r["correspondence"] in ("-", correspondence)]
    out = []
    for rd in result["renderers"]:
        mine = [r for r in rows if r.get("renderer", "paper") == rd]
        entry = {"renderer": rd, "seconds_per_frame": sum(r["seconds_per_frame"] for r in mine) / max(len(mine), 1)}
        for edit in EDITS:
            rest = [r["psnr_object"] for r in mine if r["edit"] == edit and r["pose"] == "rest"]
            posed = {r["pose"]: r["psnr_object"] for r in mine
                     if r["edit"] == edit and r["pose"] != "rest" and r["magnitude"] == 1.0}
            if not rest or not posed:
                continue
            worst = min(posed, key=posed.get)
            entry[edit] = {"rest": rest[0], "worst_pose": worst, "gap": rest[0] - posed[worst],
                           "within": sum(rest[0] - v <= 3.0 for v in posed.values()), "poses": len(posed),
                           "gaps": {p: rest[0] - v for p, v in posed.items()}}
        out.append(entry)
    return out


def markdown(per_scene: dict[str, list[dict]], head: str) -> str:
    """The table: a row per scene and renderer."""
    lines = [head, "", "| scene | renderer | geometry: rest / worst pose, gap | retexture: rest / worst pose, gap | "
             "poses within 3 dB (geometry, retexture) | s/frame |", "|---|---|---|---|---|---|"]
    for scene, entries in per_scene.items():
        for e in entries:
            cells = []
            for edit in EDITS:
                g = e.get(edit)
                cells.append("–" if g is None else f"{g['rest']:.2f} / {g['worst_pose']} {g['gap']:.2f}")
            within = ", ".join(f"{e[x]['within']}/{e[x]['poses']}" if x in e else "–" for x in EDITS)
            lines.append(f"| {scene} | {e['renderer']} | {cells[0]} | {cells[1]} | {within} | "
                         f"{e['seconds_per_frame']:.3f} |")
    return "\n".join(lines) + "\n"


def fit_command(work: Path, name: str, threads: int, samples: list[str], budget: list[str], fit_args: str = "",
                tag: str = "", downscale: int = 1) -> list[str]:
    """`python -m` arguments of the scene library bench that makes scene `name` in `work` and its stage-1 fit:
    the default fit, or with fit_args under tag (the model file `tools.bench.scenes.model_path` names); with
    downscale N > 1 the scene is made at N x SIZE and fitted with `--downscale N` (from N x finer images)."""
    if downscale > 1:
        fit_args = f"{fit_args} --downscale {downscale}".strip()
    cmd = ["tools.bench.scenes", "--work", str(work), "--scenes", name, "--no-pair", "--threads", str(threads),
           *samples, *budget]
    if downscale > 1:
        cmd += ["--size", str(SIZE * downscale)]
    return cmd + (["--fit-args", fit_args, "--tag", tag] if fit_args else [])


def scene_size(scene: Path) -> int | None:
    """The image width of a made scene (its scene.json), None when it has none."""
    try:
        return int(json.loads((scene / "scene.json").read_text())["camera"]["width"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def main(argv=None) -> int:
    from core.frames.edited import EditConfig
    from tools.bench import add_samples, run_command, samples_flag, write_json
    from tools.bench.scenes import model_path
    from tools.eval_edits import default_renderer
    from tools.machine import machine_line
    from tools.scenes.library import scene_names

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, help="folder for the scenes, models and results (reused between runs)")
    ap.add_argument("--scenes", default=",".join(scene_names()), help="comma-separated library scenes (default: all)")
    ap.add_argument("--steps", type=int, default=1000, help="stage-1 steps per fit (0: --minutes instead)")
    ap.add_argument("--minutes", type=float, default=10.0, help="stage-1 budget per fit when --steps is 0")
    ap.add_argument("--renderers", default=None,
                    help="comma-separated eval-edits renderer variants (default: paper and the default renderer)")
    ap.add_argument("--poses", default=None, help="comma-separated poses (default: every pose of each scene)")
    ap.add_argument("--correspondences", default=None,
                    help="eval-edits --correspondences (default: the default one, `pointgt render`'s; the table "
                         "reads the first one's retexture; the JSON keeps every correspondence's rows)")
    ap.add_argument("--views", type=int, default=4, help="test views per case (eval-edits --views)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per fit and per atlas fit")
    ap.add_argument("--fit-args", default="", help="more `pointgt fit` flags for every stage-1 fit (one string; "
                    "needs --tag), e.g. --fit-args=--view-dependent (a lone flag needs the =)")
    ap.add_argument("--tag", default="", help="name of the --fit-args setting: its models and edit figures are "
                    "SCENE.TAG.* files beside the defaults'")
    ap.add_argument("--atlas-args", default="", help="more `pointgt atlas` flags (one string), e.g. "
                    "--atlas-args='--atlas-texels-per-pixel 4'; a model's atlas is fitted once, so use a fresh --work")
    ap.add_argument("--downscale", type=int, default=1,
                    help=f"fit from images this many times finer: every scene made at this times {SIZE}², fitted, "
                         "its atlas fitted and its edits scored with `--downscale` this (the models train and are "
                         "scored at " f"{SIZE}²; `pointgt fit`'s --train-scales auto trains on the finer levels); "
                         "a tag names the models (ds N unless --tag), so use a fresh --work")
    ap.add_argument("--json", default=None, help="write all figures here")
    ap.add_argument("--markdown", default=None, help="write the table here")
    add_samples(ap)
    args = ap.parse_args(argv)
    if bool(args.fit_args) != bool(args.tag):
        ap.error("--fit-args and --tag go together (the tag names the setting's files)")
    if not 1 <= args.downscale <= 8:
        ap.error(f"--downscale: a whole factor from 1 to 8, got {args.downscale}")
    if args.downscale > 1 and not args.tag:
        args.tag = f"ds{args.downscale}"
    renderers = args.renderers or f"paper,{default_renderer()}"
    args.correspondences = args.correspondences or EditConfig.correspondence
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m"]
    budget = ["--steps", str(args.steps)] if args.steps else ["--minutes", str(args.minutes)]
    atlas = args.atlas_args or "defaults"
    scale = f" from {SIZE * args.downscale}² images (--downscale {args.downscale})" if args.downscale > 1 else ""
    head = (f"```\n{machine_line()}\nstage 1: {' '.join(budget)}, {args.threads} thread(s){scale}; atlas: {atlas}; "
            f"eval-edits: magnitude 1, {args.views} views, {args.correspondences}, T = 1, soft blend\n```")
    print(head, flush=True)
    per_scene, figures = {}, {}
    for name in [s for s in args.scenes.split(",") if s]:
        model = model_path(work, name, None, args.tag)
        made = scene_size(work / name)
        if made is not None and made != SIZE * args.downscale:
            raise SystemExit(f"{work / name}: made at {made}², this run fits from {SIZE * args.downscale}² images "
                             f"(--downscale {args.downscale}); use a fresh --work")
        ds = ["--downscale", str(args.downscale)] if args.downscale > 1 else []
        if not model.exists():
            run_command(py + fit_command(work, name, args.threads, samples_flag(args.samples), budget, args.fit_args,
                                         args.tag, args.downscale), print, check=True)
        if not model.with_suffix(".atlas_history.json").exists():
            run_command(py + ["tools.cli", "atlas", str(model), str(work / name), "--atlas-threads",
                              str(args.threads), "--no-progress", *ds, *shlex.split(args.atlas_args)], print,
                        check=True)
        out = work / f"{name}{'.' + args.tag if args.tag else ''}.edits.json"
        want = [r for r in renderers.split(",") if r]
        have = json.loads(out.read_text()) if out.exists() else None
        stale = have is None or have.get("renderers") != want or have.get("correspondences", ["deform-aware"]) != \
            args.correspondences.split(",")
        if stale or (args.poses and have.get("poses") != args.poses.split(",")):
            cmd = py + ["tools.cli", "eval-edits", str(model), "--scene", str(work / name), "--magnitudes", "1",
                        "--views", str(args.views), "--temperatures", "1", "--correspondences", args.correspondences,
                        "--renderers", ",".join(want), "--json", str(out), *ds]
            if args.poses:
                cmd += ["--poses", args.poses]
            run_command(cmd, print, check=True)
            have = json.loads(out.read_text())
        per_scene[name] = gaps(have)
        figures[name] = per_scene[name]
        print("\n".join(markdown({name: per_scene[name]}, "").strip().splitlines()[-len(want):]), flush=True)
        write_json(args.json, {"machine": head, "scenes": figures})
    table = markdown(per_scene, head)
    print(table)
    if args.markdown:
        Path(args.markdown).write_text(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
