"""core/util/workers.py: workers with one torch thread each, and a module's batch split over them (forward and
backward equal to the module on the calling thread, to float rounding)."""
from concurrent.futures import wait

import pytest
import torch

from core.points.decoders import UNetDecoder
from core.util.workers import cpu_workers, piece_sizes, pool, run, split_batch, split_rows

RTOL = 1e-5


def _close(a, b, what):
    err = float((a - b).abs().max()) / max(float(b.abs().max()), 1e-12)
    assert err <= RTOL, f"{what}: relative error {err:.2e}"


def test_workers_run_one_torch_thread_and_leave_the_callers_setting():
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        p = pool(2)
        futures = [p.submit(torch.get_num_threads) for _ in range(4)]
        wait(futures)
        assert [f.result() for f in futures] == [1] * 4
        assert torch.get_num_threads() == 2
        assert cpu_workers(torch.zeros(1), 5, None) == 2  # torch's threads unless given
        assert cpu_workers(torch.zeros(1), 1, None) == 1  # never more than the pieces
        assert cpu_workers(torch.zeros(1), 5, 4) == 4
        assert cpu_workers(torch.zeros(1, device="meta"), 5, 4) == 1  # off the CPU: the calling thread
    finally:
        torch.set_num_threads(before)
    assert run(lambda a, b: a * b, [(2, 3), (4, 5), (6, 7)]) == [6, 20, 42]  # in order
    assert run(lambda: torch.is_grad_enabled(), [(), ()]) == [False, False]
    assert run(lambda: torch.is_grad_enabled(), [(), ()], grad=True) == [True, True]
    with pytest.raises(ZeroDivisionError):  # a worker's error reaches the caller
        run(lambda a: 1 // a, [(1,), (0,)])


@pytest.mark.parametrize("batch,workers", [(16, 2), (5, 3), (3, 8), (1, 2)])
def test_split_batch_equals_the_module_forward_and_backward(batch, workers):
    torch.manual_seed(batch)
    net = UNetDecoder(4 + 8, alpha=True, residual=True)
    for p in net.parameters():  # non-zero last layers: every parameter gets a gradient
        torch.nn.init.normal_(p, std=0.1)
    x = torch.rand(batch, 12, 16, 16)
    g = torch.randn(batch, 4, 16, 16)
    outs = []
    for split in (False, True):
        xi = x.clone().requires_grad_()
        net.zero_grad()
        y = split_batch(net, xi, workers) if split else net(xi)
        y.backward(g)
        outs.append((y.detach(), xi.grad, {n: p.grad.clone() for n, p in net.named_parameters()}))
    (y0, gx0, gp0), (y1, gx1, gp1) = outs
    _close(y1, y0, "output")
    _close(gx1, gx0, "input gradient")
    for name in gp0:
        _close(gp1[name], gp0[name], name)
    with torch.no_grad():  # no gradients: the calling thread
        assert torch.equal(split_batch(net, x, workers), net(x))
    # an input that needs no gradient: the parameters' gradients still flow
    net.zero_grad()
    split_batch(net, x, workers).backward(g)
    for name, p in net.named_parameters():
        _close(p.grad, gp0[name], name + " (input without gradient)")


@pytest.mark.parametrize("rows,workers", [(40, 2), (7, 3), (2, 8)])
def test_split_rows_equals_fn_forward_and_backward(rows, workers):
    """Rows through a small function with row inputs (one without gradient, one integer), a shared tensor and a
    parameter used directly, several outputs (one integer): the same outputs and gradients as on the calling
    thread."""
    torch.manual_seed(rows)
    lin = torch.nn.Linear(3, 3)
    table = torch.randn(10, 3)
    a, b = torch.randn(rows, 3), torch.randn(rows, 3)
    idx = torch.randint(0, 10, (rows, 4))

    def fn(a, b, idx, table):
        g = table.index_select(0, idx.reshape(-1)).view(*idx.shape, 3)       # [r, 4, 3]
        y = lin(a[:, None] * g).sum(1) + b.square()
        return [y, torch.softmax(y, 1), idx >= 5]

    outs = []
    for split in (False, True):
        ai, ti = a.clone().requires_grad_(), table.clone().requires_grad_()
        lin.zero_grad()
        y, s, m = (split_rows(fn, [ai, b, idx], [ti], list(lin.parameters()), workers) if split
                   else fn(ai, b, idx, ti))
        (y.square().sum() + (s * torch.arange(3.0)).sum()).backward()
        outs.append((y.detach(), s.detach(), m, ai.grad, ti.grad, [p.grad.clone() for p in lin.parameters()]))
    (y0, s0, m0, ga0, gt0, gp0), (y1, s1, m1, ga1, gt1, gp1) = outs
    _close(y1, y0, "output")
    _close(s1, s0, "softmax")
    assert torch.equal(m1, m0) and not m1.requires_grad
    _close(ga1, ga0, "row input gradient")
    _close(gt1, gt0, "shared input gradient")
    for a1, a0 in zip(gp1, gp0):
        _close(a1, a0, "parameter gradient")


def test_piece_sizes_share_rows_or_cost_evenly():
    assert piece_sizes(10, 3) == [3, 3, 4]
    assert piece_sizes(2, 3) == [0, 1, 1]  # fewer rows than pieces: some are empty
    cost = torch.tensor([10.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert piece_sizes(8, 2, cost) == [1, 7]  # half of the work is in the first row
    assert piece_sizes(8, 4, torch.zeros(8)) == [1, 1, 1, 5]  # no work: every piece still gets a row
    sizes = piece_sizes(1000, 2, torch.arange(1000.0))
    assert sum(sizes) == 1000 and 700 <= sizes[0] <= 710  # cost grows along the rows: the first piece is longer
    assert piece_sizes(5, 5, torch.rand(5)) == [1] * 5
