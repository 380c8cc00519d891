"""RUL evaluation on the ``rul`` split: true k vs the full online flow vs the physics reference.

Definitions (fractions, as every metrics.json of phm_torch):
* reference RUL q5/q50/q95: damage propagation stopped by the true assessment function (LF model);
* Delta_RUL (the paper's uncertainty of the physics model, its eq. for Delta_RUL) = (q95 - q5) / q50 of the
  reference: the full width of the 90 % interval relative to the expected RUL;
* err_RUL = |q50_est - q50_ref| / q50_ref, for the estimate from the true k (surrogate classifier) and
  from the full flow (signal -> gappy -> MLP -> k_hat -> RUL);
* band coverage: fraction of reference q50 inside the estimate's [q5, q95];
* vectors already faulty under the reference (q50_ref = 0) are excluded from relative errors and
  counted in ``rul_reference_faulty``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class RULComparison:
    """Per-vector RULs [h], (N, 3) each (5/50/95 %)."""

    reference: torch.Tensor
    true_k: torch.Tensor
    full_flow: torch.Tensor

    def metrics(self) -> dict[str, float]:
        ref = self.reference
        usable = ref[:, 1] > 0
        r = ref[usable]

        def err(est: torch.Tensor) -> torch.Tensor:
            return (est[usable, 1] - r[:, 1]).abs() / r[:, 1]

        def coverage(est: torch.Tensor) -> float:
            e = est[usable]
            inside = (r[:, 1] >= e[:, 0]) & (r[:, 1] <= e[:, 2])
            return float(inside.double().mean()) if inside.numel() else float("nan")

        delta = (r[:, 2] - r[:, 0]) / r[:, 1]
        ff = self.full_flow[usable]
        finite = torch.isfinite(ff[:, 1])
        return {
            "rul_err_median_true_k": float(err(self.true_k).median()) if usable.any() else float("nan"),
            "rul_err_median_full_flow": float(err(self.full_flow)[finite].median()) if finite.any() else float("nan"),
            "rul_uncertainty_median": float(delta.median()) if usable.any() else float("nan"),
            "rul_band_coverage_true_k": coverage(self.true_k),
            "rul_band_coverage_full_flow": coverage(self.full_flow),
            "rul_underestimate_fraction": float((ff[finite, 1] < r[finite, 1]).double().mean())
            if finite.any()
            else float("nan"),
            "rul_err_median_hours_true_k": float((self.true_k[usable, 1] - r[:, 1]).abs().median())
            if usable.any()
            else float("nan"),
            "rul_reference_faulty": int((~usable).sum()),
            "rul_untrustworthy_full_flow": int((~torch.isfinite(self.full_flow[:, 1])).sum()),
            "rul_vectors": int(ref.shape[0]),
        }
