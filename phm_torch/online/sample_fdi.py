"""The FDI network with the gappy least squares folded into its first layer, for a complete set of samples.

For a complete set of samples the gappy estimate is linear, ``alpha = S (f - mean)``, and so is the network's input
scaling, ``(alpha - c) / s``. Both fold into the first layer, ``W1' = W1 diag(1/s) S`` and
``b1' = b1 - W1 ((S mean + c) / s)``: the FDI of a complete record is then the network alone (a linear layer, tanh,
the output layer and its clamp). In TorchScript every operation costs a few microseconds, and the gappy layer's
ten (the finiteness test, the solve, the residual) were most of the paper configuration's 62 us FDI.

A noise-aware network told no level (what :meth:`~phm_torch.online.OnlinePipeline.k_hat_of_samples` tells it: its
``default_noise``) has a constant noise input, which folds into the first bias. An ensemble (or a noise-aware
network) is folded in two stages instead, because one (members x hidden, n_w) first layer over every sample would be
4 MB for the pretrained pipeline's four 256-neuron members on 1000 samples, read for each record: ``a = S (f - mean)``
(n_m outputs), then the members' first layers stacked into one ``(members x hidden, n_m)`` layer, their deeper and
output layers as batched products, the clamp and the mean (the pretrained FDI: 175 -> 70 us on one record).

Records with a missing sample and a Bayesian gappy layer (its estimate depends on the noise) take the layers as they
are.
"""

from __future__ import annotations

import torch
from torch import nn


def _empty(dtype: torch.dtype) -> torch.Tensor:
    """An empty buffer: a slot the other fold leaves unused."""
    return torch.zeros(0, dtype=dtype)


def _as_members(fdi: nn.Module) -> tuple[torch.Tensor, ...]:
    """(w_in (M, width, H), b_in (M, 1, H), w_deep (L-1, M, H, H), b_deep (L-1, M, 1, H), w_out (M, H, 8),
    b_out (M, 1, 8)) of an FDIEnsemble (detached views of its own weights: a saved file stores them once), or of an
    FDIMLP as an ensemble of one (copies)."""
    if hasattr(fdi, "w_in"):
        return tuple(t.detach() for t in (fdi.w_in, fdi.b_in, fdi.w_deep, fdi.b_deep, fdi.w_out, fdi.b_out))
    h = fdi.hidden.weight.shape[0]
    deep = [layer.weight.detach().T for layer in fdi.deeper]
    w_deep = torch.stack(deep).unsqueeze(1) if deep else fdi.hidden.weight.new_zeros(0, 1, h, h)
    b_deep = (
        torch.stack([layer.bias.detach() for layer in fdi.deeper]).view(-1, 1, 1, h)
        if deep
        else fdi.hidden.weight.new_zeros(0, 1, 1, h)
    )
    return (
        fdi.hidden.weight.detach().T.unsqueeze(0).clone(),
        fdi.hidden.bias.detach().view(1, 1, h).clone(),
        w_deep.clone(),
        b_deep.clone(),
        fdi.output.weight.detach().T.unsqueeze(0).clone(),
        fdi.output.bias.detach().view(1, 1, -1).clone(),
    )


class FoldedFDI(nn.Module):
    """k_hat (B, 8) from a complete set of selected samples (B, n_points) [A], the gappy layer folded in.

    Args:
        gappy: the pipeline's :class:`~phm_torch.surrogates.gappy_pod.GappyPOD` layer.
        fdi: its FDI network, an :class:`~phm_torch.surrogates.fdi_mlp.FDIMLP` or an
            :class:`~phm_torch.surrogates.fdi_ensemble.FDIEnsemble`. A plain FDIMLP folds into one first layer over
            the samples; a noise-aware one (at its ``default_noise``) or an ensemble in two stages (the module note).
            A Bayesian gappy layer, or another network, is not folded (``folded`` False; the module is then never
            called).

    Every weight is a copy derived from the two layers (non-persistent buffers): the pipeline's state dict is
    unchanged, and a pipeline rebuilt from its parts derives them again.
    """

    def __init__(self, gappy: nn.Module, fdi: nn.Module):
        super().__init__()
        linear_gappy = hasattr(gappy, "solve_matrix") and not bool(getattr(gappy, "bayesian", False))
        hidden = getattr(fdi, "hidden", None)
        known = isinstance(hidden, nn.Linear) or hasattr(fdi, "w_in")
        noise_input = bool(getattr(fdi, "noise_input", False))
        self.folded = linear_gappy and known
        self.two_stage = self.folded and (noise_input or hasattr(fdi, "w_in"))
        self.n_members, self.n_hidden = 1, 1
        buffers = dict.fromkeys(
            ("proj", "centre", "first_weight", "first_bias", "deep_weight", "deep_bias", "out_weight", "out_bias"),
            _empty(torch.float32),
        )
        if self.folded:
            with torch.no_grad():
                buffers = self._fold(gappy, fdi, noise_input)
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)

    def _fold(self, gappy: nn.Module, fdi: nn.Module, noise_input: bool) -> dict[str, torch.Tensor]:
        f64 = torch.float64
        w_in, b_in, w_deep, b_deep, w_out, b_out = _as_members(fdi)
        dtype = w_in.dtype
        m, _, h = w_in.shape
        n_m = int(gappy.solve_matrix.shape[0])
        solve, mean = gappy.solve_matrix.to(f64), gappy.mean_hat.to(f64)  # (n_m, n_w), (n_w,)
        centre, scale = fdi.in_center.to(f64), fdi.in_scale.to(f64)
        w = w_in.to(f64)
        bias = b_in.to(f64).reshape(m, h) - torch.einsum("i,mih->mh", centre[:n_m] / scale[:n_m], w[:, :n_m])
        if noise_input:  # the level k_hat_of_samples tells it: the network's default, held to its trained range
            level = min(max(float(fdi.default_noise), 0.0), float(fdi.max_noise))
            bias = bias + (level - centre[n_m]) / scale[n_m] * w[:, n_m]
        first = (w[:, :n_m] / scale[:n_m, None]).permute(0, 2, 1).reshape(m * h, n_m)  # acts on S (f - mean)
        out = {"proj": _empty(dtype), "centre": _empty(dtype)}
        if self.two_stage:
            self.n_members, self.n_hidden = int(m), int(h)
            out.update(  # the gappy layer's own buffers where the dtype allows: stored once in a saved file
                proj=gappy.solve_matrix.detach().to(dtype),
                centre=gappy.mean_hat.detach().to(dtype),
                first_weight=first.to(dtype),
                first_bias=bias.reshape(m * h).to(dtype),
                deep_weight=w_deep,
                deep_bias=b_deep,
                out_weight=w_out,
                out_bias=b_out,
            )
            return out
        # one plain network: one first layer over the samples, W1 diag(1/s) S, the mean folded into its bias
        out.update(
            first_weight=(first @ solve).to(dtype),
            first_bias=(bias.reshape(h) - first @ (solve @ mean)).to(dtype),
            deep_weight=w_deep[:, 0].transpose(1, 2).contiguous(),  # back to F.linear's (out, in)
            deep_bias=b_deep[:, 0, 0],
            out_weight=w_out[0].T.contiguous(),
            out_bias=b_out.reshape(-1),
        )
        return out

    def forward(self, samples: torch.Tensor) -> torch.Tensor:
        """k_hat (B, 8) in [0, 1] from complete samples (B, n_points) [A] in the layers' dtype."""
        if self.two_stage:
            a = torch.nn.functional.linear(samples - self.centre, self.proj)
            h = torch.tanh(torch.nn.functional.linear(a, self.first_weight, self.first_bias))
            h = h.view(samples.shape[0], self.n_members, self.n_hidden).transpose(0, 1)
            for i in range(self.deep_weight.shape[0]):
                h = torch.tanh(torch.baddbmm(self.deep_bias[i], h, self.deep_weight[i]))
            return torch.baddbmm(self.out_bias, h, self.out_weight).clamp(0.0, 1.0).mean(0)
        h = torch.tanh(torch.nn.functional.linear(samples, self.first_weight, self.first_bias))
        for i in range(self.deep_weight.shape[0]):
            h = torch.tanh(torch.nn.functional.linear(h, self.deep_weight[i], self.deep_bias[i]))
        return torch.nn.functional.linear(h, self.out_weight, self.out_bias).clamp(0.0, 1.0)
