"""The scene library benchmark: the default `pointgt fit` on every library scene at one budget, with the decoder
on/off pair, the scene profile's choices and the collapse guard's actions.

    python -m tools.bench.scenes --work DIR [--scenes cloth,strip,...] [--size 128] [--minutes 10 | --steps N]
        [--threads 1] [--views-train 60 --views-test 20] [--fit-args "--decoder-weight-decay 0.5" --tag wd]
        [--json OUT] [--markdown OUT]

Per scene: `pointgt make-scene NAME --out DIR/NAME` (reused when it exists), then `pointgt fit` stage 1 with the
defaults (the profile picks the decoder), then the same fit with the other decoder (`--decoder none|unet`). Each
fit is a separate process, exactly what a user runs. Reported per fit: full / object PSNR over all test views,
steps, seconds, the guard's events and verdict; per scene the blank frame's PSNR, the profile's measurements and
the default's gap to the better decoder setting. A step budget (`--steps`) keeps the pair fair on a shared machine;
`--minutes` is what users get. `--fit-args` adds `pointgt fit` flags to every fit (a trial option measured across
the library); `--tag` names that setting's model files (DIR/NAME.TAG.default.pgt), so settings never share a model; a
seed other than 0 is in the name too (DIR/NAME.s1.default.pgt).
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from tools.bench import add_samples, run_command, samples_flag, write_json
from tools.machine import machine_line


def fit_result(model: Path) -> dict:
    """Figures of one `pointgt fit --stage papr` from its model header (numpy only, no torch)."""
    from core.modelfile.pgt import read_meta

    meta = read_meta(model)
    tr = meta["train"]
    guard = tr.get("guard", {})
    prof = meta.get("profile") or {}
    return {"psnr": tr["test_all_views"]["psnr"], "psnr_object": tr["test_all_views"]["psnr_object"],
            "coverage": tr["test_all_views"].get("coverage"), "steps": tr["steps"],
            "seconds": tr["train_seconds"], "decoder": meta["model"]["decoder"],
            "blank": guard.get("blank_floor_all_views"), "guard_events": [e["action"] for e in guard.get("events", [])],
            "collapsed": guard.get("collapsed"), "declined": guard.get("declined"),
            "profile": {k: prof.get(k) for k in ("decoder", "k", "charts", "view_dependent")} if prof else None,
            "measured": {k: (prof.get("measured") or {}).get(k)
                         for k in ("pixels_per_point", "view_variation", "hull_flatness")} if prof else None}


def model_path(work: Path, scene: str, decoder: str | None, tag: str = "", seed: int = 0) -> Path:
    """Model file of a scene's fit: the default fit (decoder None) or the pair's other decoder setting, under the
    setting's tag when --fit-args are given and the seed when it is not 0 (so no two settings share a file)."""
    return work / ".".join([scene, *([tag] if tag else []), *([f"s{seed}"] if seed else []), decoder or "default",
                            "pgt"])


def markdown(rows: list[dict], header: str) -> str:
    out = [header, "",
           "| scene | profile: decoder, K, charts (pixels/point) | default full / object | blank full / object | "
           "steps (s) | guard | unet object | none object | default − best |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d = r["default"]
        p, m = d["profile"] or {}, d["measured"] or {}
        pair = {r["default"]["decoder"]: d, **{v["decoder"]: v for v in r.get("other", [])}}
        best = max(v["psnr_object"] for v in pair.values())
        guard = ", ".join(d["guard_events"]) or "–"
        if d["collapsed"]:
            guard += f"; COLLAPSED ({d['collapsed']})"
        elif d.get("declined"):
            guard += f"; DECLINED ({d['declined']})"
        fmt = lambda k: f"{pair[k]['psnr_object']:.2f}" if k in pair else "–"  # noqa: E731
        out.append(f"| {r['scene']} | {p.get('decoder')}, {p.get('k')}, {p.get('charts')} "
                   f"({(m.get('pixels_per_point') or 0):.2f}) | {d['psnr']:.2f} / {d['psnr_object']:.2f} | "
                   f"{d['blank']['psnr']:.2f} / {d['blank']['psnr_object']:.2f} | {d['steps']} ({d['seconds']:.0f}) | "
                   f"{guard} | {fmt('unet')} | {fmt('none')} | {d['psnr_object'] - best:+.2f} |")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    from tools.scenes.library import scene_names

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, help="folder for the scenes and models (reused between runs)")
    ap.add_argument("--scenes", default=",".join(scene_names()), help="comma-separated library scenes (default: all)")
    ap.add_argument("--size", type=int, default=128, help="image size of the scenes")
    ap.add_argument("--views-train", type=int, default=60)
    ap.add_argument("--views-test", type=int, default=20)
    ap.add_argument("--minutes", type=float, default=10.0, help="stage-1 budget per fit (the default fit's)")
    ap.add_argument("--steps", type=int, default=None, help="a step budget instead (fair on a shared machine)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per fit")
    ap.add_argument("--seed", type=int, default=0)
    add_samples(ap)
    ap.add_argument("--no-pair", action="store_true", help="only the default fit (no decoder on/off pair)")
    ap.add_argument("--fit-args", default="", help="more `pointgt fit` flags for every fit (one string)")
    ap.add_argument("--tag", default="", help="name of the --fit-args setting: its model files are "
                                              "NAME.TAG.default.pgt and NAME.TAG.<decoder>.pgt (needed with "
                                              "--fit-args)")
    ap.add_argument("--json", default=None, help="write all figures here")
    ap.add_argument("--markdown", default=None, help="write the table here")
    args = ap.parse_args(argv)
    if args.fit_args and not args.tag:
        ap.error("--fit-args: name the setting with --tag (the model files' name)")
    if args.tag and not all(c.isalnum() or c in "-_" for c in args.tag):
        ap.error(f"--tag {args.tag!r}: letters, digits, '-' and '_' only (it names files)")
    extra = shlex.split(args.fit_args)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m", "tools.cli"]
    budget = ["--steps", str(args.steps), "--minutes", "0"] if args.steps else ["--minutes", str(args.minutes)]
    head = (f"{machine_line()}\nbudget per fit: {' '.join(budget)}, {args.threads} thread(s), {args.size}², "
            f"{args.views_train} train / {args.views_test} test views, seed {args.seed}"
            + (f"\nfit flags: {args.fit_args}" if extra else ""))
    print(head, flush=True)
    rows = []
    for name in [s for s in args.scenes.split(",") if s]:
        scene = work / name
        if not (scene / "scene.json").exists():
            run_command(py + ["make-scene", name, "--out", str(scene), "--size", str(args.size), "--views-train",
                              str(args.views_train), "--views-test", str(args.views_test), "--views-val", "0",
                              *samples_flag(args.samples)], print)
        row = {"scene": name, "other": []}
        common = ["fit", str(scene), "--stage", "papr", "--threads", str(args.threads), "--no-progress",
                  "--seed", str(args.seed), "--allow-blank", *budget, *extra]
        default = model_path(work, name, None, args.tag, args.seed)
        if not default.exists():
            run_command(py + common + ["--out", str(default)], print)
        row["default"] = fit_result(default)
        if not args.no_pair:
            other = "none" if row["default"]["decoder"] == "unet" else "unet"
            path = model_path(work, name, other, args.tag, args.seed)
            if not path.exists():
                run_command(py + common + ["--out", str(path), "--decoder", other], print)
            row["other"].append(fit_result(path))
        rows.append(row)
        print(markdown([row], "").strip().splitlines()[-1], flush=True)
        write_json(args.json, {"machine": head, "rows": rows})
    table = markdown(rows, "```\n" + head + "\n```")
    print(table)
    if args.markdown:
        Path(args.markdown).write_text(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
