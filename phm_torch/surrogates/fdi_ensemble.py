"""An ensemble of FDI networks: the mean of several networks of the :class:`FDIMLP` architecture.

The members differ only by their initial weights and are trained side by side (each on its own loss,
the same batches). Their errors are partly independent where the signal is a rough function of k (several
heavy faults at once), so the mean is more accurate than any member: on the paper-scale HF store, four
2 x 256 networks give err_k 5.2 % against 5.8 % for one (docs/surrogates.md).

The members' weights are stacked along a leading member dimension, so the whole ensemble is a few
batched matrix products (``baddbmm``) rather than one small network after another: four 2 x 256
members cost 41 us per eager call against 26 us for one network, and the gappy POD before them is shared.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .fdi_mlp import (
    FDIMLP,
    N_FAULTS,
    check_architecture,
    check_noise_input,
    network_inputs,
    normalization_rows,
    scaling_statistics,
)


def _uniform(shape: tuple[int, ...], fan_in: int) -> nn.Parameter:
    """nn.Linear's default initialisation, U(-1/sqrt(fan_in), 1/sqrt(fan_in)), for weights and biases."""
    bound = 1.0 / math.sqrt(fan_in)
    return nn.Parameter(torch.empty(shape).uniform_(-bound, bound))


class FDIEnsemble(nn.Module):
    """alpha (B, n_m) [, noise (B,)] -> k_hat (B, 8) in [0, 1], the mean of ``n_members`` tansig networks.

    Each member is an :class:`FDIMLP` (``n_layers`` hidden layers of ``n_hidden`` tansig neurons, satlin
    output); all share the input scaling fitted by :meth:`set_normalization`.

    Args:
        n_inputs, n_hidden, n_outputs, input_scaling, n_layers, noise_input, default_noise, max_noise: as
            :class:`FDIMLP`.
        n_members: networks in the ensemble (>= 2; one network is an :class:`FDIMLP`).
    """

    def __init__(
        self,
        n_inputs: int,
        n_hidden: int = 20,
        n_outputs: int = N_FAULTS,
        input_scaling: str = "minmax",
        n_layers: int = 1,
        n_members: int = 4,
        noise_input: bool = False,
        default_noise: float = 0.01,
        max_noise: float = 0.1,
    ):
        super().__init__()
        if isinstance(n_members, bool) or not isinstance(n_members, int) or n_members < 2:
            raise ValueError(f"fdi.n_members of an ensemble must be an integer >= 2, got {n_members!r}")
        check_architecture(
            n_inputs=n_inputs, n_hidden=n_hidden, n_outputs=n_outputs, n_layers=n_layers, input_scaling=input_scaling
        )
        m = n_members
        self.noise_input = check_noise_input(noise_input, default_noise, max_noise)
        self.default_noise, self.max_noise = float(default_noise), float(max_noise)
        width = n_inputs + int(noise_input)
        self.w_in, self.b_in = _uniform((m, width, n_hidden), width), _uniform((m, 1, n_hidden), width)
        self.w_deep = _uniform((n_layers - 1, m, n_hidden, n_hidden), n_hidden)
        self.b_deep = _uniform((n_layers - 1, m, 1, n_hidden), n_hidden)
        self.w_out, self.b_out = _uniform((m, n_hidden, n_outputs), n_hidden), _uniform((m, 1, n_outputs), n_hidden)
        self.n_inputs, self.n_hidden, self.n_outputs = n_inputs, n_hidden, n_outputs
        self.n_layers, self.n_members, self.input_scaling = n_layers, n_members, input_scaling
        self.register_buffer("in_center", torch.zeros(width))
        self.register_buffer("in_scale", torch.ones(width))

    def set_normalization(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> FDIEnsemble:
        """Fit the shared input scaling to training coefficients (N, n_m) (and, noise-aware, their noise
        levels (N,)); returns self."""
        rows = normalization_rows(alpha, noise, self.noise_input)
        center, scale = scaling_statistics(rows, self.input_scaling, self.in_center.shape[0])
        self.in_center, self.in_scale = center.to(self.in_center), scale.to(self.in_scale)
        return self

    def member_preactivations(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """(n_members, B, 8) each member's output before saturation: each member is fitted on its own."""
        x = (
            network_inputs(alpha, noise, self.noise_input, self.default_noise, self.max_noise) - self.in_center
        ) / self.in_scale
        h = torch.tanh(torch.baddbmm(self.b_in, x.unsqueeze(0).expand(self.n_members, -1, -1), self.w_in))
        for i in range(self.n_layers - 1):
            h = torch.tanh(torch.baddbmm(self.b_deep[i], h, self.w_deep[i]))
        return torch.baddbmm(self.b_out, h, self.w_out)

    def forward(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """k_hat (B, 8) in [0, 1]: the mean of the members' saturated (satlin) outputs (``noise`` as
        :meth:`FDIMLP.forward`)."""
        return self.member_preactivations(alpha, noise).clamp(0.0, 1.0).mean(0)

    def extra_repr(self) -> str:
        return (
            f"n_members={self.n_members}, n_inputs={self.n_inputs}, n_hidden={self.n_hidden}, "
            f"n_layers={self.n_layers}, n_outputs={self.n_outputs}, input_scaling={self.input_scaling}, "
            f"noise_input={self.noise_input}"
        )


def build_fdi_network(
    n_inputs: int, n_hidden: int, n_layers: int = 1, n_members: int = 1, **kwargs: object
) -> FDIMLP | FDIEnsemble:
    """One :class:`FDIMLP` (``n_members=1``, the paper) or an :class:`FDIEnsemble` of ``n_members``."""
    if n_members == 1:
        return FDIMLP(n_inputs, n_hidden, n_layers=n_layers, **kwargs)  # type: ignore[arg-type]
    return FDIEnsemble(n_inputs, n_hidden, n_layers=n_layers, n_members=n_members, **kwargs)  # type: ignore[arg-type]
