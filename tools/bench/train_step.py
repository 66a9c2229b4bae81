"""Stage-1 step time: seconds per training step of `pointgt fit` on a scene, per key-MLP path, split by part.

    python -m tools.bench.train_step --data DIR [--steps 40] [--repeats 3] [--paths torch,chunked]
        [--workers 0] [--op-threads 0] [--views-per-step 1] [--threads 1 | --fit-threads 1,2] [--json OUT]

Loads the scene and applies the scene profile as `pointgt fit` does, then runs `fit_points` for --steps steps with
each `--key-path` (and each `--workers` and `--op-threads` value: `TrainConfig.workers`, e.g. `1,0` to compare
the step on the training thread alone with its rays and decoder patches shared out to one worker per
thread, `TrainConfig.op_threads`, and `TrainConfig.views_per_step`) in turn (A B A B ..., so a drifting
machine load hits all alike), --repeats times. Per fit:
wall seconds per step from the fit's own training clock (what a `--minutes` budget counts) and CPU seconds per
step of the training thread (the fit's thread CPU time minus its test evaluations and set-up — visual hull,
spacing, blank floor, footprint — over the steps; on a shared machine this moves less than the wall clock; with
several threads it leaves out the other threads' work, so compare the wall clock there). A
short fit per path first, not counted, takes the one-time costs (numba compile, first convolutions). The parts of the step are timed by
wrapping the core functions the step calls (thread CPU time): patch sampling, neighbour search, attention
forward, shading, decoder forward, the regularizers, backward, Adam; the rest of the step is "other". With
workers (`--workers`, `--fit-threads` above 1) CPU seconds are the training thread's, the workers' CPU time for
their pieces is its own column, and the critical path adds to the training thread's CPU time the slowest piece of
each join: what a step takes on otherwise idle cores, measured in CPU time, which a loaded machine moves far less
than the wall clock (on one thread it is the CPU time). Medians over the repeats are printed with the machine
line, the wall clock's min and max too.
"""
from __future__ import annotations

import contextlib
import itertools
import statistics
import time

PARTS = ("data", "search", "attend", "shade", "decoder", "regularizers", "backward", "adam", "other")


@contextlib.contextmanager
def _timed(owner, name: str, part: str, clock: dict):
    """Replace owner.name by a wrapper adding its thread CPU time to clock[part], restored on exit."""
    fn = getattr(owner, name)

    def wrapper(*a, **kw):
        if clock.get("_outer"):  # inside a test evaluation or the set-up: counted there
            return fn(*a, **kw)
        outer = part.startswith("_")
        clock["_outer"] = outer
        t = time.thread_time()
        try:
            return fn(*a, **kw)
        finally:
            clock[part] = clock.get(part, 0.0) + time.thread_time() - t
            clock["_outer"] = False

    setattr(owner, name, wrapper)
    try:
        yield
    finally:
        setattr(owner, name, fn)


@contextlib.contextmanager
def _pieces(owners, clock: dict):
    """Replace `run` of each module in owners (core.util.workers.run and its imports) by a wrapper that adds, per
    call with several pieces, the CPU time of its slowest piece to clock["slowest"] and of all to clock["pieces"]."""
    import core.util.workers as workers

    run = workers.run

    def wrapper(fn, args, grad=False):
        if len(args) <= 1:
            return run(fn, args, grad)
        cpu = [0.0] * len(args)

        def timed(i, *a):
            t = time.thread_time()
            try:
                return fn(*a)
            finally:
                cpu[i] = time.thread_time() - t
        out = run(timed, [(i, *a) for i, a in enumerate(args)], grad)
        clock["slowest"] = clock.get("slowest", 0.0) + max(cpu)
        clock["pieces"] = clock.get("pieces", 0.0) + sum(cpu)
        return out

    for owner in owners:
        owner.run = wrapper
    try:
        yield
    finally:
        for owner in owners:
            owner.run = run


def time_fit(train, test, model_cfg, cfg) -> dict:
    """One fit_points run with its parts timed: dict(wall_per_step, cpu_per_step, critical_per_step,
    pieces_per_step, parts {part: CPU s per step}, steps, points). With workers (`TrainConfig.workers`),
    cpu_per_step is the training thread's alone, pieces_per_step the workers' CPU time for their pieces, and
    critical_per_step the step's critical path: the training thread's CPU time plus, at each join, the slowest
    piece's (what a step would take on idle cores); the parts timed inside a worker add its CPU time."""
    import torch

    import core.points.train as tr
    import core.util.workers as workers
    from core.points.model import PointModel

    clock: dict = {}
    wraps = [(tr, "sample_patches", "data"), (tr, "select_neighbors", "search"), (PointModel, "attend", "attend"),
             (PointModel, "shade", "shade"), (PointModel, "decode_with_alpha", "decoder"),
             (tr, "close_to_ray", "regularizers"), (tr, "close_to_surface", "regularizers"),
             (torch.Tensor, "backward", "backward"), (torch.optim.Adam, "step", "adam"),
             (tr, "evaluate", "_evaluate"), (tr, "visual_hull_points", "_setup"), (tr, "blank_floor", "_setup"),
             (tr, "training_footprint", "_setup"), (tr, "mean_spacing", "_setup")]
    with contextlib.ExitStack() as stack:
        for owner, name, part in wraps:
            stack.enter_context(_timed(owner, name, part, clock))
        stack.enter_context(_pieces((workers,), clock))
        t = time.thread_time()
        _, history = tr.fit_points(train, test, model_cfg, cfg, show_progress=False)
        total = time.thread_time() - t
    steps = max(history[-1]["step"], 1)
    step_cpu = total - clock.pop("_evaluate", 0.0) - clock.pop("_setup", 0.0)
    clock.pop("_outer", None)
    slowest, pieces = clock.pop("slowest", 0.0), clock.pop("pieces", 0.0)
    parts = {p: clock.get(p, 0.0) / steps for p in PARTS if p != "other"}
    parts["other"] = max(step_cpu / steps - sum(parts.values()), 0.0)
    return {"wall_per_step": history[-1]["seconds"] / steps, "cpu_per_step": step_cpu / steps,
            "critical_per_step": (step_cpu + slowest) / steps, "pieces_per_step": pieces / steps, "parts": parts,
            "steps": steps, "points": history[-1]["points"]}


def main(argv=None) -> int:
    from tools.bench import parse, parser, write_json

    ap = parser(__doc__)
    ap.add_argument("--data", required=True, help="dataset folder (e.g. made by `pointgt make-scene cloth`)")
    ap.add_argument("--steps", type=int, default=40, help="training steps per fit")
    ap.add_argument("--repeats", type=int, default=3, help="fits per key path (medians are reported)")
    ap.add_argument("--paths", default="torch,chunked", help="comma-separated key paths (TrainConfig.key_path)")
    ap.add_argument("--fit-threads", default=None,
                    help="comma-separated TrainConfig.threads values run in turn (e.g. 1,2; default: --threads)")
    ap.add_argument("--workers", default="0",
                    help="comma-separated TrainConfig.workers values, each run with every key path")
    ap.add_argument("--op-threads", default="0",
                    help="comma-separated TrainConfig.op_threads values, each run with every other variant")
    ap.add_argument("--views-per-step", default="1",
                    help="comma-separated TrainConfig.views_per_step values, each run with every other variant")
    ap.add_argument("--seed", type=int, default=0)
    args = parse(ap, argv, threads=1)

    from core.atlas.config import AtlasConfig
    from core.images.dataset import load_dataset
    from core.points.model import ModelConfig
    from core.points.train import TrainConfig
    from core.profile import apply_profile, scene_profile
    from tools.machine import machine_info, machine_line

    data = load_dataset(args.data, splits=("train", "test"), required=("train", "test"), progress=False)
    train, test = data["train"], data["test"]
    model_cfg = ModelConfig()
    profile = scene_profile(train, seed=args.seed, device="cpu", num_points=model_cfg.num_points)
    model_cfg, _, _ = apply_profile(profile, model_cfg, AtlasConfig(), set())
    fit_threads = args.fit_threads.split(",") if args.fit_threads else [args.threads]
    lists = {"threads": [int(t) for t in fit_threads], "key_path": args.paths.split(","),
             "workers": [int(k) for k in args.workers.split(",")],
             "op_threads": [int(k) for k in args.op_threads.split(",")],
             "views_per_step": [int(k) for k in args.views_per_step.split(",")]}
    variants = [dict(zip(lists, v)) for v in itertools.product(*lists.values())]
    shown = [k for k, vals in lists.items() if len(vals) > 1] or ["key_path"]  # what tells the variants apart
    name = [", ".join(str(v[k]) if k == "key_path" else f"{k.replace('_', ' ')} {v[k]}" for k in shown)
            for v in variants]
    print(machine_line())
    print(f"{args.data}: {len(train)} train views at {train.width}x{train.height}; decoder {model_cfg.decoder}, "
          f"K {model_cfg.k}; {args.steps} steps per fit, {args.repeats} fits per variant, "
          f"{', '.join(map(str, lists['threads']))} thread(s)")
    runs: dict = {n: [] for n in name}
    for v in variants:  # warm-up, not counted: one-time costs (compiled neighbour search, first convolutions)
        time_fit(train, test, model_cfg, TrainConfig(steps=3, eval_every=1e9, **v))
    for _ in range(args.repeats):
        for n, v in zip(name, variants):
            cfg = TrainConfig(steps=args.steps, eval_every=1e9, seed=args.seed, **v)
            runs[n].append(time_fit(train, test, model_cfg, cfg))
    keys = ("wall_per_step", "cpu_per_step", "critical_per_step", "pieces_per_step")
    med = {p: {**{k: statistics.median(r[k] for r in rs) for k in keys},
               "wall_range": [min(r["wall_per_step"] for r in rs), max(r["wall_per_step"] for r in rs)],
               "parts": {k: statistics.median(r["parts"][k] for r in rs) for k in PARTS}} for p, rs in runs.items()}
    print("| variant | wall s/step min / median / max | CPU s/step | critical path s/step | worker pieces CPU "
          "s/step | " + " | ".join(PARTS) + " |")
    print("|---|---|---|---|---|" + "---|" * len(PARTS))
    for p, m in med.items():
        share = " | ".join(f"{1000 * m['parts'][k]:.1f} ms ({100 * m['parts'][k] / m['cpu_per_step']:.0f} %)"
                           for k in PARTS)
        lo, hi = m["wall_range"]
        print(f"| {p} | {lo:.3f} / {m['wall_per_step']:.3f} / {hi:.3f} | {m['cpu_per_step']:.3f} | "
              f"{m['critical_per_step']:.3f} | {m['pieces_per_step']:.3f} | {share} |")
    names = list(runs)
    if len(names) > 1:
        ref = med[names[0]]
        for p in names[1:]:
            print(f"{p} vs {names[0]}: wall x {ref['wall_per_step'] / med[p]['wall_per_step']:.2f} faster, "
                  f"critical path x {ref['critical_per_step'] / med[p]['critical_per_step']:.2f}")
    print(machine_line())
    write_json(args.json, {"machine": machine_info(), "data": args.data, "steps": args.steps,
                           "threads": lists["threads"], "model": model_cfg.__dict__, "median": med, "runs": runs})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
