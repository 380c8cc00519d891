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

**Noise-aware networks** (``noise_input=True``, this project's option): the record's relative measurement
noise (std over its RMS current, :meth:`~phm_torch.online.OnlinePipeline.noise_level`) joins the
coefficients as one more input. Trained end to end on samples with random noise levels (the level of
each record given), the network learns how far to trust the fine detail of the coefficients: on the paper
store a network trained so keeps its noise-free accuracy and loses far less of it at 3-10 % noise than one
trained on clean or on noisy records without the level (docs/surrogates.md). A caller that does not know
the level gets ``default_noise`` (the rated noise of the training configuration).
"""

from __future__ import annotations

import torch
from torch import nn

from ..faults import N_FAULTS

SCALINGS = ("minmax", "robust")


def check_architecture(input_scaling: str, **sizes: int) -> None:
    """ValueError naming the field unless every size is a positive integer and the scaling is known."""
    if input_scaling not in SCALINGS:
        raise ValueError(f"fdi.input_scaling must be one of {list(SCALINGS)}, got {input_scaling!r}")
    for name, v in sizes.items():
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"fdi.{name} must be a positive integer, got {v!r}")


def check_noise_input(noise_input: bool, default_noise: float, max_noise: float) -> bool:
    """``noise_input`` as a bool; ValueError naming the field for a non-bool or bad noise levels."""
    if not isinstance(noise_input, bool):
        raise ValueError(f"fdi.noise_input must be true or false, got {noise_input!r}")
    if not max_noise > 0:
        raise ValueError(f"fdi.max_noise must be > 0, got {max_noise!r}")
    if not 0 <= default_noise <= max_noise:
        raise ValueError(f"fdi.default_noise must be in [0, max_noise={max_noise!r}], got {default_noise!r}")
    return noise_input


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


def network_inputs(
    alpha: torch.Tensor, noise: torch.Tensor | None, noise_input: bool, default_noise: float, max_noise: float
) -> torch.Tensor:
    """The network's input rows (B, n_m [+ 1]): alpha (B, n_m), with the relative noise (B,) as the last
    column for a noise-aware network (``default_noise`` where ``noise`` is None), held to the trained
    range [0, ``max_noise``] (a level outside it would ask the network to extrapolate)."""
    if not noise_input:
        return alpha
    if noise is None:
        level = torch.full((alpha.shape[0],), default_noise, dtype=alpha.dtype, device=alpha.device)
    else:
        level = noise.to(alpha.dtype).clamp(0.0, max_noise)
    return torch.cat([alpha, level.reshape(alpha.shape[0], 1)], 1)


def normalization_rows(alpha: torch.Tensor, noise: torch.Tensor | None, noise_input: bool) -> torch.Tensor:
    """Rows for the input-scaling statistics: alpha (N, n_m), and for a noise-aware network the training
    noise levels (N,), which it then requires."""
    if not noise_input:
        return alpha
    if noise is None or noise.shape != alpha.shape[:1]:
        raise ValueError(
            f"a noise-aware network's input scaling needs the training noise levels (N,) = "
            f"({alpha.shape[0]},), got {None if noise is None else tuple(noise.shape)}"
        )
    return torch.cat([alpha, noise.to(alpha.dtype).reshape(-1, 1)], 1)


class FDIMLP(nn.Module):
    """alpha (B, n_m) [, noise (B,)] -> k_hat (B, 8) in [0, 1].

    Args:
        n_inputs: number of POD coefficients n_m.
        n_hidden: tansig neurons per hidden layer (paper: 20).
        n_outputs: fault parameters (8).
        input_scaling: ``minmax`` or ``robust`` (see the module note).
        n_layers: hidden layers (paper: 1). On the paper-scale HF store a second layer lowers err_k
            where several large faults interact (docs/surrogates.md).
        noise_input: the record's relative noise level is one more input (see the module note).
        default_noise: relative noise assumed when a caller gives none (noise-aware networks only).
        max_noise: largest relative noise the network was trained with; larger levels are held there.
    """

    def __init__(
        self,
        n_inputs: int,
        n_hidden: int = 20,
        n_outputs: int = N_FAULTS,
        input_scaling: str = "minmax",
        n_layers: int = 1,
        noise_input: bool = False,
        default_noise: float = 0.01,
        max_noise: float = 0.1,
    ):
        super().__init__()
        check_architecture(
            n_inputs=n_inputs, n_hidden=n_hidden, n_outputs=n_outputs, n_layers=n_layers, input_scaling=input_scaling
        )
        self.input_scaling = input_scaling
        self.n_inputs, self.n_hidden, self.n_outputs, self.n_layers = n_inputs, n_hidden, n_outputs, n_layers
        self.n_members = 1  # the interface of FDIEnsemble: one network
        self.noise_input = check_noise_input(noise_input, default_noise, max_noise)
        width = n_inputs + int(noise_input)
        self.hidden = nn.Linear(width, n_hidden)
        # the first layer keeps its name, so single-layer state dicts (the paper's network) load unchanged
        self.deeper = nn.ModuleList([nn.Linear(n_hidden, n_hidden) for _ in range(n_layers - 1)])
        self.output = nn.Linear(n_hidden, n_outputs)
        self.register_buffer("in_center", torch.zeros(width))
        self.register_buffer("in_scale", torch.ones(width))
        # plain attributes, saved in the bundle's meta: the state dicts of networks without the input stay
        self.default_noise, self.max_noise = float(default_noise), float(max_noise)

    def set_normalization(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> FDIMLP:
        """Fit the input scaling to training coefficients (N, n_m) (and, noise-aware, their noise levels
        (N,)); returns self."""
        rows = normalization_rows(alpha, noise, self.noise_input)
        center, scale = scaling_statistics(rows, self.input_scaling, self.in_center.shape[0])
        self.in_center, self.in_scale = center.to(self.in_center), scale.to(self.in_scale)
        return self

    def preactivation(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """Output-layer values before saturation (B, 8)."""
        x = network_inputs(alpha, noise, self.noise_input, self.default_noise, self.max_noise)
        h = torch.tanh(self.hidden((x - self.in_center) / self.in_scale))
        for layer in self.deeper:
            h = torch.tanh(layer(h))
        return self.output(h)

    def member_preactivations(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """(1, B, 8): :meth:`preactivation` as the one member of an ensemble (the training loss's input)."""
        return self.preactivation(alpha, noise).unsqueeze(0)

    def forward(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """k_hat (B, 8) in [0, 1] (satlin output). ``noise`` (B,): the records' relative noise, used by a
        noise-aware network (None: ``default_noise``), ignored otherwise."""
        return self.preactivation(alpha, noise).clamp(0.0, 1.0)

    def extra_repr(self) -> str:
        return (
            f"n_inputs={self.n_inputs}, n_hidden={self.n_hidden}, n_layers={self.n_layers}, "
            f"n_outputs={self.n_outputs}, input_scaling={self.input_scaling}, noise_input={self.noise_input}"
        )
