"""The FDI network with the gappy least squares folded into its first layer, for a complete set of samples.

For a complete set of samples the gappy estimate is linear, ``alpha = S (f - mean)``, and so is the network's input
scaling, ``(alpha - c) / s``. Both fold into the first layer, ``W1' = W1 diag(1/s) S`` and
``b1' = b1 - W1 ((S mean + c) / s)``: the FDI of a complete record is then the network alone (a linear layer, tanh,
the output layer and its clamp). In TorchScript every operation costs a few microseconds, and the gappy layer's
ten (the finiteness test, the solve, the residual) were most of the paper configuration's 62 us FDI.

Records with a missing sample, noise-aware networks and ensembles take the layers as they are
(:meth:`~phm_torch.online.OnlinePipeline.k_hat_of_samples`): the fold needs a fixed linear map from the samples to
the network's inputs.
"""

from __future__ import annotations

import torch
from torch import nn


class FoldedFDI(nn.Module):
    """k_hat (B, 8) from a complete set of selected samples (B, n_points) [A], the gappy layer folded in.

    Args:
        gappy: the pipeline's :class:`~phm_torch.surrogates.gappy_pod.GappyPOD` layer.
        fdi: its FDI network; an :class:`~phm_torch.surrogates.fdi_mlp.FDIMLP` that is not noise-aware is folded
            (``folded``), anything else is not (and this module is then never called).

    Every weight is a copy derived from the two layers (non-persistent buffers): the pipeline's state dict is
    unchanged, and a pipeline rebuilt from its parts derives them again.
    """

    def __init__(self, gappy: nn.Module, fdi: nn.Module):
        super().__init__()
        hidden = getattr(fdi, "hidden", None)
        self.folded = (
            isinstance(hidden, nn.Linear)
            and not bool(getattr(fdi, "noise_input", True))
            and hasattr(gappy, "solve_matrix")
            and not bool(getattr(gappy, "bayesian", False))
        )
        empty = torch.zeros(0)
        first_weight = first_bias = out_weight = out_bias = deep_weight = deep_bias = empty
        if self.folded:
            with torch.no_grad():
                solve = gappy.solve_matrix.to(torch.float64)  # (n_m, n_w)
                scale, w = fdi.in_scale.to(torch.float64), hidden.weight.to(torch.float64)
                scaled = w / scale  # W1 diag(1/s), (n_h, n_m)
                first_weight = scaled @ solve
                first_bias = (
                    hidden.bias.to(torch.float64)
                    - scaled @ (solve @ gappy.mean_hat.to(torch.float64))
                    - w @ (fdi.in_center.to(torch.float64) / scale)
                ).to(hidden.weight.dtype)
                first_weight = first_weight.to(hidden.weight.dtype)
                out_weight, out_bias = fdi.output.weight.detach().clone(), fdi.output.bias.detach().clone()
                n_h = hidden.weight.shape[0]
                deep_weight = torch.stack([layer.weight.detach() for layer in fdi.deeper]) if len(fdi.deeper) else None
                deep_bias = torch.stack([layer.bias.detach() for layer in fdi.deeper]) if len(fdi.deeper) else None
                if deep_weight is None:
                    deep_weight = hidden.weight.new_zeros(0, n_h, n_h)
                    deep_bias = hidden.weight.new_zeros(0, n_h)
        for name, value in (
            ("first_weight", first_weight),
            ("first_bias", first_bias),
            ("deep_weight", deep_weight),
            ("deep_bias", deep_bias),
            ("out_weight", out_weight),
            ("out_bias", out_bias),
        ):
            self.register_buffer(name, value, persistent=False)

    def forward(self, samples: torch.Tensor) -> torch.Tensor:
        """k_hat (B, 8) in [0, 1] from complete samples (B, n_points) [A] in the layers' dtype."""
        h = torch.tanh(torch.nn.functional.linear(samples, self.first_weight, self.first_bias))
        for i in range(self.deep_weight.shape[0]):
            h = torch.tanh(torch.nn.functional.linear(h, self.deep_weight[i], self.deep_bias[i]))
        return torch.nn.functional.linear(h, self.out_weight, self.out_bias).clamp(0.0, 1.0)
