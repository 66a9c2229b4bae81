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
