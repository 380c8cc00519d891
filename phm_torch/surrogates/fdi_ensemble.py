"""An ensemble of FDI networks: the mean of several :class:`FDIMLP` of one architecture.

The members differ only by their initial weights and are trained side by side (each on its own loss,
the same batches). Their errors are partly independent where the signal is a rough function of k (several
heavy faults at once), so the mean is more accurate than any member: on the paper-scale HF store, four
2 x 256 networks give err_k 4.9 % against 5.3-6.1 % for each alone (docs/surrogates.md). The cost is
one network evaluation per member online; the gappy POD before them is shared.
"""

from __future__ import annotations

import torch
from torch import nn

from .fdi_mlp import FDIMLP, N_FAULTS


class FDIEnsemble(nn.Module):
    """alpha (B, n_m) -> k_hat (B, 8) in [0, 1], the mean of ``n_members`` FDIMLP outputs.

    Args:
        n_inputs, n_hidden, n_outputs, input_scaling, n_layers: as :class:`FDIMLP`, shared by every member.
        n_members: networks in the ensemble (>= 2; one network is an :class:`FDIMLP`).
    """

    def __init__(self, n_inputs: int, n_hidden: int = 20, n_outputs: int = N_FAULTS, input_scaling: str = "minmax",
                 n_layers: int = 1, n_members: int = 4):
        super().__init__()
        if isinstance(n_members, bool) or not isinstance(n_members, int) or n_members < 2:
            raise ValueError(f"fdi.n_members of an ensemble must be an integer >= 2, got {n_members!r}")
        self.members = nn.ModuleList([FDIMLP(n_inputs, n_hidden, n_outputs, input_scaling, n_layers)
                                      for _ in range(n_members)])
        self.n_inputs, self.n_hidden, self.n_outputs = n_inputs, n_hidden, n_outputs
        self.n_layers, self.n_members, self.input_scaling = n_layers, n_members, input_scaling

    def set_normalization(self, alpha: torch.Tensor) -> FDIEnsemble:
        """Fit every member's input scaling to training coefficients (N, n_m); returns self."""
        for member in self.members:
            member.set_normalization(alpha)
        return self

    def member_preactivations(self, alpha: torch.Tensor) -> torch.Tensor:
        """(n_members, B, 8) each member's output before saturation: each member is fitted on its own."""
        return torch.stack([member.preactivation(alpha) for member in self.members])

    def forward(self, alpha: torch.Tensor) -> torch.Tensor:
        """k_hat (B, 8) in [0, 1]: the mean of the members' saturated outputs."""
        total = torch.zeros(alpha.shape[0], self.n_outputs, dtype=alpha.dtype, device=alpha.device)
        for member in self.members:
            total = total + member(alpha)
        return total / self.n_members

    def extra_repr(self) -> str:
        return f"n_members={self.n_members}"


def build_fdi_network(n_inputs: int, n_hidden: int, n_layers: int = 1, n_members: int = 1,
                      **kwargs: object) -> FDIMLP | FDIEnsemble:
    """One :class:`FDIMLP` (``n_members=1``, the paper) or an :class:`FDIEnsemble` of ``n_members``."""
    if n_members == 1:
        return FDIMLP(n_inputs, n_hidden, n_layers=n_layers, **kwargs)  # type: ignore[arg-type]
    return FDIEnsemble(n_inputs, n_hidden, n_layers=n_layers, n_members=n_members, **kwargs)  # type: ignore[arg-type]
