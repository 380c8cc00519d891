"""The seed paper's FDI network: POD coefficients -> fault vector k.

One hidden layer (``n_layers``, default 1; more is this project's option) of ``tansig`` neurons (tansig(x) = 2 / (1 + exp(-2x)) - 1, which is tanh) and an
output layer of saturated-linear neurons (``satlin``: clamp to [0, 1]), as MATLAB's feedforward net.
The inputs are scaled per coefficient with statistics of the training set, kept as buffers so the
module is self-contained: ``minmax`` maps the training range to [-1, 1] (MATLAB's ``mapminmax``, the
paper's setting); ``robust`` centres on the median and divides by the interquartile range / 1.349 (the
std of a Gaussian). POD coefficients of actuator currents are heavy-tailed (a few extreme faults draw
hundreds of amperes), so with ``minmax`` most signals crowd into a small part of [-1, 1]; ``robust``
spreads them (on the LF development store: LM err_k 0.14 -> 0.10, see docs/surrogates.md).

Training uses :meth:`preactivation` (the output before saturation): for a target in [0, 1],
|clamp(z) - k| <= |z - k|, so fitting z also fits the saturated output, and the gradient does not
vanish on saturated outputs.
"""

from __future__ import annotations

import torch
from torch import nn

N_FAULTS = 8
SCALINGS = ("minmax", "robust")


def check_architecture(input_scaling: str, **sizes: int) -> None:
    """ValueError naming the field unless every size is a positive integer and the scaling is known."""
    if input_scaling not in SCALINGS:
        raise ValueError(f"fdi.input_scaling must be one of {list(SCALINGS)}, got {input_scaling!r}")
    for name, v in sizes.items():
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"fdi.{name} must be a positive integer, got {v!r}")


def scaling_statistics(alpha: torch.Tensor, input_scaling: str, n_inputs: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(center, scale), each (n_m,) float64, of training coefficients alpha (N, n_m) for ``input_scaling``."""
    if alpha.ndim != 2 or alpha.shape[1] != n_inputs:
        raise ValueError(f"alpha must be (N, {n_inputs}), got {tuple(alpha.shape)}")
    a = alpha.detach().to(torch.float64)
    if input_scaling == "minmax":
        lo, hi = a.amin(0), a.amax(0)
        center, scale = (hi + lo) / 2, (hi - lo) / 2
    else:
        q = torch.quantile(a, torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64), dim=0)
        center, scale = q[1], (q[2] - q[0]) / 1.349
    return center, scale.clamp(min=1e-12)


class FDIMLP(nn.Module):
    """alpha (B, n_m) -> k_hat (B, 8) in [0, 1].

    Args:
        n_inputs: number of POD coefficients n_m.
        n_hidden: tansig neurons per hidden layer (paper: 20).
        n_outputs: fault parameters (8).
        input_scaling: ``minmax`` or ``robust`` (see the module note).
        n_layers: hidden layers (paper: 1). On the paper-scale HF store a second layer lowers err_k
            where several large faults interact (docs/surrogates.md).
    """

    def __init__(self, n_inputs: int, n_hidden: int = 20, n_outputs: int = N_FAULTS, input_scaling: str = "minmax",
                 n_layers: int = 1):
        super().__init__()
        check_architecture(n_inputs=n_inputs, n_hidden=n_hidden, n_outputs=n_outputs, n_layers=n_layers,
                           input_scaling=input_scaling)
        self.input_scaling = input_scaling
        self.n_inputs, self.n_hidden, self.n_outputs, self.n_layers = n_inputs, n_hidden, n_outputs, n_layers
        self.n_members = 1                  # the interface of FDIEnsemble: one network
        self.hidden = nn.Linear(n_inputs, n_hidden)
        # the first layer keeps its name, so single-layer state dicts (the paper's network) load unchanged
        self.deeper = nn.ModuleList([nn.Linear(n_hidden, n_hidden) for _ in range(n_layers - 1)])
        self.output = nn.Linear(n_hidden, n_outputs)
        self.register_buffer("in_center", torch.zeros(n_inputs))
        self.register_buffer("in_scale", torch.ones(n_inputs))

    def set_normalization(self, alpha: torch.Tensor) -> FDIMLP:
        """Fit the input scaling to training coefficients (N, n_m); returns self."""
        center, scale = scaling_statistics(alpha, self.input_scaling, self.n_inputs)
        self.in_center, self.in_scale = center.to(self.in_center), scale.to(self.in_scale)
        return self

    def preactivation(self, alpha: torch.Tensor) -> torch.Tensor:
        """Output-layer values before saturation (B, 8)."""
        h = torch.tanh(self.hidden((alpha - self.in_center) / self.in_scale))
        for layer in self.deeper:
            h = torch.tanh(layer(h))
        return self.output(h)

    def member_preactivations(self, alpha: torch.Tensor) -> torch.Tensor:
        """(1, B, 8): :meth:`preactivation` as the one member of an ensemble (the training loss's input)."""
        return self.preactivation(alpha).unsqueeze(0)

    def forward(self, alpha: torch.Tensor) -> torch.Tensor:
        """k_hat (B, 8) in [0, 1] (satlin output)."""
        return self.preactivation(alpha).clamp(0.0, 1.0)

    def extra_repr(self) -> str:
        return (f"n_inputs={self.n_inputs}, n_hidden={self.n_hidden}, n_layers={self.n_layers}, "
                f"n_outputs={self.n_outputs}, input_scaling={self.input_scaling}")
