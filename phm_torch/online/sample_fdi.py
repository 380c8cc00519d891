"""The FDI alone, from the selected samples to k_hat, with the gappy least squares folded into the first layer.

For a complete set of samples the gappy estimate is linear, ``alpha = S (f - mean)``, and so is the network's input
scaling, ``(alpha - c) / s``. Both fold into the first layer, ``W1' = W1 diag(1/s) S`` and
``b1' = b1 - W1 ((S mean + c) / s)``: the FDI of a complete record is then the network alone (a linear layer, tanh,
the output layer and its clamp). In TorchScript every operation costs a few microseconds, and the gappy layer's
ten (the finiteness test, the solve, the residual) were most of the paper configuration's 62 us FDI.

Records with a missing sample, noise-aware networks and ensembles take the layers as they are (the gappy layer, then
the network): the fold needs a fixed linear map from the samples to the network's inputs.
"""

from __future__ import annotations

import torch
from torch import nn


class SampleFDI(nn.Module):
    """k_hat (B, 8) from the selected samples (B, n_points) [A]: :attr:`gappy` then :attr:`fdi`, folded when it can.

    Args:
        gappy: the pipeline's :class:`~phm_torch.surrogates.gappy_pod.GappyPOD` layer.
        fdi: its FDI network; an :class:`~phm_torch.surrogates.fdi_mlp.FDIMLP` that is not noise-aware is folded.

    The folded weights are derived (non-persistent buffers), so the pipeline's state dict is unchanged.
    """

    __constants__ = ("folded",)  # TorchScript compiles only the path that applies (an ensemble has no first layer)

    def __init__(self, gappy: nn.Module, fdi: nn.Module):
        super().__init__()
        self.gappy, self.fdi = gappy, fdi
        hidden = getattr(fdi, "hidden", None)
        self.folded = (
            isinstance(hidden, nn.Linear)
            and not bool(getattr(fdi, "noise_input", True))
            and hasattr(gappy, "solve_matrix")
            and not bool(getattr(gappy, "bayesian", False))
        )
        if self.folded:
            with torch.no_grad():
                solve = gappy.solve_matrix.to(torch.float64)  # (n_m, n_w)
                scale = fdi.in_scale.to(torch.float64)
                w1 = hidden.weight.to(torch.float64) / scale  # W1 diag(1/s), (n_h, n_m)
                weight = w1 @ solve
                bias = (
                    hidden.bias.to(torch.float64)
                    - w1 @ (solve @ gappy.mean_hat.to(torch.float64))
                    - (hidden.weight.to(torch.float64) @ (fdi.in_center.to(torch.float64) / scale))
                )
            dtype = hidden.weight.dtype
            self.register_buffer("first_weight", weight.to(dtype), persistent=False)
            self.register_buffer("first_bias", bias.to(dtype), persistent=False)
        else:
            self.register_buffer("first_weight", torch.zeros(0), persistent=False)
            self.register_buffer("first_bias", torch.zeros(0), persistent=False)

    def forward(self, samples: torch.Tensor) -> torch.Tensor:
        """k_hat (B, 8) in [0, 1] from samples (B, n_points) [A] at the selected times; NaN = missing."""
        samples = samples.to(self.gappy.modes_hat.dtype)
        if self.folded and bool(torch.isfinite(samples).all()):
            h = torch.tanh(torch.nn.functional.linear(samples, self.first_weight, self.first_bias))
            for layer in self.fdi.deeper:
                h = torch.tanh(layer(h))
            return self.fdi.output(h).clamp(0.0, 1.0)
        alpha, _ = self.gappy(samples)
        return self.fdi(alpha)
