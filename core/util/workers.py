"""CPU worker threads with one torch thread each, for work split into a few large independent pieces.

torch splits each operation over its CPU threads; for the many small operations of a training step that means a
thread barrier per operation, and when other processes hold the cores a barrier waits for a descheduled thread
(a stage-1 step on two threads of a loaded 2-core machine took 2.4x the one-thread time). Pieces of work run on
these workers instead, each piece on one thread with one torch thread: one wait per piece, not per operation. torch
releases the GIL inside its operations, so the workers run in parallel.
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import torch

_POOLS: dict[int, ThreadPoolExecutor] = {}
_LOCK = threading.Lock()


def _one_torch_thread(ready: threading.Barrier) -> None:
    """Worker initialiser: this thread's torch operations run on one thread (its own OpenMP / MKL setting; the
    first call makes torch's lazy per-thread set-up happen before, so that it cannot undo the setting later)."""
    torch.get_num_threads()
    torch.set_num_threads(1)
    ready.wait()


def pool(n: int) -> ThreadPoolExecutor:
    """The process-wide pool of n worker threads with one torch thread each, started on first use."""
    with _LOCK:
        p = _POOLS.get(n)
        if p is None:
            caller = torch.get_num_threads()
            ready = threading.Barrier(n + 1)
            p = ThreadPoolExecutor(n, thread_name_prefix="pointgt-worker", initializer=_one_torch_thread,
                                   initargs=(ready,))
            for _ in range(n):  # start every worker now (the pool starts one per submitted task)
                p.submit(int)
            ready.wait()
            torch.set_num_threads(caller)  # set_num_threads in a worker also moved torch's process default
            _POOLS[n] = p
        return p


def cpu_workers(t: torch.Tensor, pieces: int, workers: int | None) -> int:
    """How many workers share `pieces` pieces of work on tensors like t: `workers` (None: torch's CPU thread
    count), at most one per piece; 1 (the calling thread) off the CPU."""
    if t.device.type != "cpu":
        return 1
    n = torch.get_num_threads() if workers is None else int(workers)
    return max(1, min(n, pieces))


def run(fn, args: list[tuple], grad: bool = False) -> list:
    """[fn(*a) for a in args], one call per worker (in order; the calling thread alone for one call). Grad mode is
    per thread: the workers run with it off, or on with grad=True."""
    if len(args) <= 1:
        return [fn(*a) for a in args]

    def task(a):
        with torch.set_grad_enabled(grad):
            return fn(*a)
    futures = [pool(len(args)).submit(task, a) for a in args]
    return [f.result() for f in futures]


class _SplitBatch(torch.autograd.Function):
    """module(x) with x's batch split into pieces, one per worker, forward and backward; the parameters'
    gradients are summed over the pieces in order."""

    @staticmethod
    def forward(ctx, x, module, sizes, *params):
        def piece(xi):
            xi = xi.detach().requires_grad_(ctx.needs_input_grad[0])
            return xi, module(xi)
        ctx.pieces = run(piece, [(xi,) for xi in x.split(sizes)], grad=True)
        ctx.params = params
        return torch.cat([y.detach() for _, y in ctx.pieces])

    @staticmethod
    def backward(ctx, gy):
        params = [p for p in ctx.params if p.requires_grad]

        def piece(xi, y, g):
            inputs = ([xi] if xi.requires_grad else []) + params
            return torch.autograd.grad(y, inputs, g, allow_unused=True)
        sizes = [y.shape[0] for _, y in ctx.pieces]
        grads = run(piece, [(xi, y, g) for (xi, y), g in zip(ctx.pieces, gy.split(sizes))])
        ctx.pieces = None
        gx = torch.cat([g[0] for g in grads]) if ctx.needs_input_grad[0] else None
        k = 1 if ctx.needs_input_grad[0] else 0
        summed = []
        for j in range(len(params)):
            parts = [g[k + j] for g in grads if g[k + j] is not None]
            summed.append(sum(parts[1:], parts[0].clone()) if parts else None)
        it = iter(summed)
        return (gx, None, None, *(next(it) if p.requires_grad else None for p in ctx.params))


def split_batch(module: torch.nn.Module, x: torch.Tensor, workers: int | None = None) -> torch.Tensor:
    """module(x) for x [B, ...] with the batch shared out to worker threads (contiguous pieces, one per worker;
    `cpu_workers`), gradients included: the same numbers as module(x) to float rounding when the module treats
    batch items independently (no batch statistics). One worker (or grad off): module(x) on the calling thread."""
    n = cpu_workers(x, x.shape[0], workers)
    if n <= 1 or not torch.is_grad_enabled():
        return module(x)
    b = x.shape[0]
    sizes = [(i + 1) * b // n - i * b // n for i in range(n)]
    return _SplitBatch.apply(x, module, sizes, *module.parameters())


class _SplitRows(torch.autograd.Function):
    """fn over row pieces on the workers, outputs concatenated; gradients to the row inputs concatenated, to the
    shared inputs and params summed over the pieces in order."""

    @staticmethod
    def forward(ctx, fn, sizes, n_rows, n_shared, *tensors):
        rows, shared, params = tensors[:n_rows], tensors[n_rows:n_rows + n_shared], tensors[n_rows + n_shared:]
        need = ctx.needs_input_grad[4:]

        def piece(*row_pieces):
            ins = [t.detach().requires_grad_(need[i] and t.is_floating_point())
                   for i, t in enumerate((*row_pieces, *shared))]
            return ins, fn(*ins)
        ctx.pieces = run(piece, list(zip(*(t.split(sizes) for t in rows))), grad=True)
        ctx.params, ctx.n_rows, ctx.n_shared = params, n_rows, n_shared
        outs = [torch.cat([out[j].detach() for _, out in ctx.pieces]) for j in range(len(ctx.pieces[0][1]))]
        ctx.mark_non_differentiable(*[o for o in outs if not o.is_floating_point()])
        return tuple(outs)

    @staticmethod
    def backward(ctx, *grads):
        n_rows, n_shared = ctx.n_rows, ctx.n_shared
        params = [p for p in ctx.params if p.requires_grad]
        sizes = [out[0].shape[0] for _, out in ctx.pieces]

        def piece(ins, outs, gs):
            pairs = [(o, g) for o, g in zip(outs, gs) if o.requires_grad and g is not None]
            wrt = [t for t in ins if t.requires_grad] + params
            got = (torch.autograd.grad([o for o, _ in pairs], wrt, [g for _, g in pairs], allow_unused=True)
                   if pairs and wrt else [None] * len(wrt))
            # a row input this piece did not use gets zeros: the pieces are concatenated
            row_ins = [i < n_rows for i, t in enumerate(ins) if t.requires_grad] + [False] * len(params)
            return [torch.zeros_like(w) if g is None and r else g for g, w, r in zip(got, wrt, row_ins)]
        split = [g.split(sizes) if g is not None else [None] * len(sizes) for g in grads]
        res = run(piece, [(ins, outs, [s[i] for s in split]) for i, (ins, outs) in enumerate(ctx.pieces)])
        needs = [t.requires_grad for t in ctx.pieces[0][0]]
        ctx.pieces = None
        n_ins = sum(needs)

        def total(parts, like_rows):
            if like_rows:  # row inputs: one piece per worker, concatenated
                return torch.cat(parts)
            parts = [p for p in parts if p is not None]
            return sum(parts[1:], parts[0].clone()) if parts else None
        out, k = [], 0
        for i, need in enumerate(needs):
            if need:
                out.append(total([r[k] for r in res], i < n_rows))
                k += 1
            else:
                out.append(None)
        it = iter(total([r[n_ins + j] for r in res], False) for j in range(len(params)))
        out += [next(it) if p.requires_grad else None for p in ctx.params]
        return (None, None, None, None, *out)


def piece_sizes(r: int, n: int, cost: torch.Tensor | None = None) -> list[int]:
    """Sizes of n contiguous pieces of r rows: equal row counts, or with cost [r] (≥ 0, the work of each row)
    equal shares of the total cost (each piece at least one row when r ≥ n)."""
    if cost is None or r < n:
        return [(i + 1) * r // n - i * r // n for i in range(n)]
    c = torch.cumsum(cost.detach().double().clamp_min(0.0).cpu(), 0)
    goals = c[-1] * torch.arange(1, n, dtype=torch.float64) / n
    cuts = torch.searchsorted(c, goals).tolist()
    bounds = [0]
    for i, cut in enumerate(cuts):  # strictly increasing, room left for the pieces after
        bounds.append(min(max(cut + 1, bounds[-1] + 1), r - (n - 1 - i)))
    bounds.append(r)
    return [b - a for a, b in zip(bounds[:-1], bounds[1:])]


def split_rows(fn, rows: list[torch.Tensor], shared: list[torch.Tensor], params: list[torch.Tensor],
               workers: int | None = None, cost: torch.Tensor | None = None) -> list[torch.Tensor]:
    """fn(*row_pieces, *shared) -> list of tensors [r, ...], run on the rows' pieces (rows: tensors [R, ...] split
    along dim 0 into contiguous pieces, one per worker (`cpu_workers`), of equal cost [R] when given, else of equal
    row counts (`piece_sizes`)) and concatenated back to [R, ...], gradients
    included: to rows (concatenated), to shared tensors and to params (parameters fn uses directly, e.g. a
    module's weights), summed over the pieces. The same numbers as fn on the calling thread to float rounding
    when fn treats rows independently. One worker (or grad off): fn on the calling thread. fn must not start
    workers itself."""
    n = cpu_workers(rows[0], rows[0].shape[0], workers)
    if n <= 1 or not torch.is_grad_enabled():
        return list(fn(*rows, *shared))
    sizes = piece_sizes(rows[0].shape[0], n, cost)
    return list(_SplitRows.apply(fn, sizes, len(rows), len(shared), *rows, *shared, *params))
