"""How the online programs are lowered for AOTInductor on CPU: graph rewrites and compiler options that make the
compiled step faster without changing what it computes beyond float32 rounding.

* The classifiers' tanh as :func:`tanh_for_inductor` (a series and an exp, 1.3 ulp): inductor's own vectorised
  tanh costs four times ATen's, and the RUL search evaluates about 13,000 per record. Not in the two scores each
  RUL crossing is interpolated between (downstream of :data:`CROSSING_MARKER`): there the rounding is magnified.
* Every matrix layer as :func:`linear_for_inductor` (``mm - (-bias)``): ``addmm`` first copies the bias into the
  output, a pass over it per layer.
* No bounds checks on the gathers (:data:`STEP_INDUCTOR_OPTIONS`), and the FDI program's products autotuned
  (:data:`FDI_INDUCTOR_OPTIONS`).

Eager ATen and the other formats keep the operations as traced: there they are the fast ones.
"""

from __future__ import annotations

import torch

# Every program: no bounds check on indirect reads. The step's gathers read the record at the pipeline's constant
# sample indices and its RUL grid at indices made in range by construction (argmax over the scan, bisection
# midpoints between two valid indices, clamps); inductor checked each one, 16 at a time through a stack buffer, and
# the step's first kernel (the gather of the selected samples) was the slowest one: +8 % records/s without the
# checks, bit-identical outputs.
STEP_INDUCTOR_OPTIONS = {"assert_indirect_indexing": False}

# The FDI program's products autotuned, inductor's own CPU GEMM kernels among the choices: one record's FDI (the
# pretrained pipeline's four 256-neuron members) took 46 us against 61 with the library's batched products alone
# (alternating, this project's 2-core machine). The step's products cannot be: the CPU GEMM template fails on
# the classifiers' weights, which are views into one flat buffer (torch 2.13).
FDI_INDUCTOR_OPTIONS = {
    "max_autotune": True,
    "max_autotune_gemm_backends": "CPP,ATEN",
    "max_autotune_report_choices_stats": False,
    "autotune_num_choices_displayed": 0,
}


CLASSIFIERS = ("classifier", "verdict_classifier")  # the pipeline's classifier modules (their tanh: for_inductor)
# the pipeline's zero buffer added to the states of each RUL crossing's two final scores
# (:meth:`~phm_torch.online.rul_propagation.RULPropagation.rul_shifted`): the scores computed from it keep the exact
# tanh. The interpolated crossing is s0 / (s0 - s1) of a grid step, so a score's rounding moves a short RUL by
# 1e-7 / (s0 - s1) steps: with the series form everywhere a third actuator's 10 h RUL moved by 2.2e-5 of its value
# against eager, 3.5e-6 with the exact tanh (6 of the 42 classifier rows of a record).
CROSSING_MARKER = "crossing_marker"

# tanh(x) / x = P(x^2) on |x| < 0.625: a degree-6 least-squares fit on 2,000 Chebyshev nodes (float64; largest
# error 1.5e-10, far below float32's 6e-8)
TANH_SPLIT = 0.625
TANH_SERIES = (
    0.9999999999416033,
    -0.333333306390829,
    0.13333205987832075,
    -0.05394696745392352,
    0.021702233685305813,
    -0.00818158339133936,
    0.0021469229639830088,
)


def tanh_for_inductor(x: torch.Tensor) -> torch.Tensor:
    """tanh(x) as inductor compiles it fast: x P(x^2) below ``TANH_SPLIT``, (1 - e) / (1 + e) with e = exp(-2|x|)
    above (no cancellation there: 1 - e >= 0.71), the sign copied. Within 1.3 float32 ulp of tanh."""
    a = x.abs()
    e = torch.exp(-2.0 * a)
    u = x * x
    series = torch.full_like(u, TANH_SERIES[-1])
    for c in TANH_SERIES[-2::-1]:
        series = series * u + c
    return torch.copysign(torch.where(a < TANH_SPLIT, a * series, (1.0 - e) / (1.0 + e)), x)


def _in_classifier(node: torch.fx.Node) -> bool:
    """Whether ``node`` was traced inside a health or verdict classifier (one of its modules is one)."""
    stack = node.meta.get("nn_module_stack") or {}
    return any(path.rsplit(".", 1)[-1] in CLASSIFIERS for path, _ in stack.values())


def for_inductor(module: torch.fx.GraphModule) -> torch.fx.GraphModule:
    """``module`` (an exported program's ``module()``) with its matrix layers as :func:`linear_for_inductor` and
    the classifiers' tanh as :func:`tanh_for_inductor`, for AOTInductor only. Inductor's vectorised tanh on CPU is
    the Sleef one, four times the cost of ATen's (1.7 against 0.4 ns per value on this project's machine) and most
    of the RUL search's time (its classifiers evaluate about 13,000 tanh per record); the series-and-exp form costs
    0.9 ns for 1.3 against 0.5 ulp (2 sigmoid(2x) - 1 costs 0.6 ns but errs by up to 3e-7 near 0). The FDI keeps
    tanh: its k_hat starts the RUL propagations, and an FDI error of 2e-7 moved near-zero RUL crossings by more
    than 1e-5 h; so do the two scores each RUL crossing is interpolated between (:data:`CROSSING_MARKER`). Eager
    ATen runs the form slower than its own tanh, so the other formats keep tanh."""
    exact = _crossing_nodes(module)
    for node in module.graph.nodes:
        if node.op != "call_function":
            continue
        if node.target is torch.ops.aten.tanh.default and _in_classifier(node) and node not in exact:
            node.target = tanh_for_inductor
        elif node.target is torch.ops.aten.linear.default and _matrix_input(node):
            node.target = linear_for_inductor
    module.recompile()
    return module


def _crossing_nodes(module: torch.fx.GraphModule) -> set[torch.fx.Node]:
    """Every node computed from the :data:`CROSSING_MARKER` buffer, the marker's additions (``x + 0``) removed
    from the graph (each use of one reads its ``x``)."""
    markers = [
        n for n in module.graph.nodes if n.op == "get_attr" and str(n.target).rsplit(".", 1)[-1] == CROSSING_MARKER
    ]
    reached: set[torch.fx.Node] = set()
    todo = [user for marker in markers for user in marker.users]
    while todo:
        node = todo.pop()
        if node not in reached:
            reached.add(node)
            todo.extend(node.users)
    for marker in markers:
        for add in list(marker.users):
            if add.target is torch.ops.aten.add.Tensor and len(add.args) == 2 and add.args[1] is marker:
                add.replace_all_uses_with(add.args[0])
                module.graph.erase_node(add)
        if not marker.users:
            module.graph.erase_node(marker)
    return reached


def _matrix_input(node: torch.fx.Node) -> bool:
    value = node.args[0].meta.get("val") if isinstance(node.args[0], torch.fx.Node) else None
    return isinstance(value, torch.Tensor) and value.dim() == 2


def linear_for_inductor(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """F.linear of a matrix x (N, in) as a product and a bias subtracted negated: inductor turns ``mm + bias`` into
    ``addmm``, which first copies the bias into every row of the output (a pass over it per layer); ``mm - (-bias)``
    (the same value in IEEE arithmetic) fuses into the next elementwise kernel instead (the pretrained pipeline's
    step: 62 such layers, +5 % records/s)."""
    y = torch.mm(x, weight.t())
    return y if bias is None else y - (-bias)
