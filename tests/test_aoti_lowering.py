"""The AOTInductor lowering rewrites (phm_torch/online/aoti_lowering.py): same numbers, other operations."""

import math

import torch
from torch import nn

from phm_torch.online.aoti_lowering import (
    TANH_SPLIT,
    for_inductor,
    linear_for_inductor,
    tanh_for_inductor,
)


def test_tanh_for_inductor_is_within_two_ulp_of_tanh_everywhere():
    g = torch.Generator().manual_seed(0)
    x = torch.cat(
        [
            torch.randn(200_000, generator=g) * 3.0,
            torch.linspace(-1.0, 1.0, 200_001),  # both sides of the split at 0.625
            torch.randn(1000, generator=g) * 1e-6,  # x itself
            torch.tensor([TANH_SPLIT, -TANH_SPLIT, 9.0, -9.0, 40.0, -40.0]),
        ]
    )
    exact = torch.tanh(x.double())
    got = tanh_for_inductor(x).double()
    ulp = torch.finfo(torch.float32).eps * exact.abs().clamp(min=torch.finfo(torch.float32).tiny)
    assert float(((got - exact).abs() / ulp).max()) < 2.0
    assert torch.equal(tanh_for_inductor(-x), -tanh_for_inductor(x))  # odd, as tanh
    special = tanh_for_inductor(torch.tensor([0.0, -0.0, math.inf, -math.inf, math.nan]))
    assert special[:4].tolist() == [0.0, 0.0, 1.0, -1.0] and math.copysign(1.0, float(special[1])) < 0
    assert math.isnan(float(special[4]))


def test_linear_for_inductor_is_the_product_plus_the_bias():
    g = torch.Generator().manual_seed(1)
    x, w, b = torch.randn(33, 8, generator=g), torch.randn(64, 8, generator=g), torch.randn(64, generator=g)
    assert torch.equal(linear_for_inductor(x, w, b), x @ w.T + b)
    assert torch.equal(linear_for_inductor(x, w), x @ w.T)
    torch.testing.assert_close(linear_for_inductor(x, w, b), nn.functional.linear(x, w, b), rtol=1e-6, atol=1e-6)


def _lowered(module: nn.Module, k: torch.Tensor) -> torch.fx.GraphModule:
    """``module`` exported with a dynamic batch on k (B, 8) and rewritten by :func:`for_inductor`."""
    batch = torch.export.Dim("batch", min=1, max=1024)
    return for_inductor(torch.export.export(module, (k,), dynamic_shapes={"k": {0: batch}}, strict=False).module())


class _Toy(nn.Module):
    """A verdict classifier and an FDI, as the pipeline names them, each a layer and a tanh."""

    def __init__(self):
        super().__init__()
        self.verdict_classifier = nn.Sequential(nn.Linear(8, 16), nn.Tanh(), nn.Linear(16, 1))
        self.fdi = nn.Sequential(nn.Linear(8, 16), nn.Tanh())

    def forward(self, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.verdict_classifier(k), self.fdi(k)


def test_for_inductor_rewrites_the_classifiers_tanh_and_every_matrix_layer_only():
    toy = _Toy().eval()
    k = torch.rand(5, 8, generator=torch.Generator().manual_seed(2))
    lowered = _lowered(toy, k)
    targets = [n.target for n in lowered.graph.nodes if n.op == "call_function"]
    assert targets.count(tanh_for_inductor) == 1  # the classifier's
    assert targets.count(torch.ops.aten.tanh.default) == 1  # the FDI's, kept: its k_hat starts the RUL
    assert targets.count(linear_for_inductor) == 3 and torch.ops.aten.linear.default not in targets
    with torch.no_grad():
        for got, ref in zip(lowered(k), toy(k)):
            torch.testing.assert_close(got, ref, rtol=1e-6, atol=1e-6)


class _Crossing(nn.Module):
    """A verdict classifier scored twice, the second time on states marked by a zero ``crossing_marker``, as the
    RUL search scores the two ends of each crossing."""

    def __init__(self):
        super().__init__()
        self.verdict_classifier = nn.Sequential(nn.Linear(8, 16), nn.Tanh(), nn.Linear(16, 1))
        self.register_buffer("crossing_marker", torch.zeros(()), persistent=False)

    def forward(self, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.verdict_classifier(k), self.verdict_classifier(2.0 * k + self.crossing_marker)


def test_for_inductor_keeps_the_crossing_scores_tanh_exact_and_drops_the_marker():
    toy = _Crossing().eval()
    k = torch.rand(5, 8, generator=torch.Generator().manual_seed(3))
    lowered = _lowered(toy, k)
    nodes = [n for n in lowered.graph.nodes if n.op in ("call_function", "get_attr")]
    targets = [n.target for n in nodes if n.op == "call_function"]
    assert targets.count(tanh_for_inductor) == 1 and targets.count(torch.ops.aten.tanh.default) == 1
    assert not any(str(n.target).endswith("crossing_marker") for n in nodes)  # the x + 0 is gone
    assert torch.ops.aten.add.Tensor not in targets
    with torch.no_grad():
        scan, ends = lowered(k)
        ref_scan, ref_ends = toy(k)
    assert torch.equal(ends, ref_ends)  # the exact tanh: the same kernels as eager here
    torch.testing.assert_close(scan, ref_scan, rtol=1e-6, atol=1e-6)
