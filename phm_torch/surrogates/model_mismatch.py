"""How the trained surrogates fare on records of a model other than the one they learned from.

The FDI network learns k from one simulator. A record from another implementation of the datasheet,
or from a bench with a physical effect that the simulator lacks, differs from the training records by
a few per cent of its range. :func:`mismatch_metrics` measures what such a difference does to the
estimates and to the health verdict, and whether the out-of-distribution checks of the online pipeline
notice it; ``scripts/fdi_model_mismatch.py`` runs it over the effect library on a store's val split.
"""

from __future__ import annotations

import torch

from .augment import noise_level, rms
from .bundle import SurrogateBundle
from .metrics import confusion, err_k, fdi_mae


def mismatch_metrics(
    bundle: SurrogateBundle, k: torch.Tensor, healthy: torch.Tensor, reference: torch.Tensor, signals: torch.Tensor
) -> dict[str, float]:
    """The surrogates on ``signals``, records of the same fault vectors as ``reference`` from another model.

    Args:
        bundle: the trained surrogates (FDI, classifier, out-of-distribution thresholds).
        k: (B, 8) the actual fault vectors.
        healthy: (B,) bool, the actual health of each vector (the assessment function's label).
        reference: (B, n_e) envelope currents [A] of the model the bundle was trained on, at ``k``.
        signals: (B, n_e) envelope currents [A] of the other model at ``k`` (the measurements).

    Returns:
        ``nrmse_median``: median over the records of RMS(signals - reference) / range(reference), the size
        of the modelling difference; ``err_k`` and ``fdi_mae_max`` (the largest per-parameter mean
        |k error|, k7 weighted by k6 as in err_k) of the FDI on ``signals``; ``chain_accuracy``, the
        verdict (``bundle.verdict_healthy``) on k_hat against ``healthy``, and which way it errs:
        ``chain_missed_fault_rate`` (of the faulty records, judged healthy) and ``chain_false_alarm_rate``
        (of the healthy, judged faulty); ``ood_rate_gappy`` (gappy residual above the
        bundle's threshold), ``ood_rate_full`` (:class:`FullSignalCheck` of the full record, as the online
        pipeline runs it) and ``ood_rate`` (either); ``n`` records.
    """
    if reference.ndim != 2 or signals.shape != reference.shape:
        raise ValueError(
            f"reference and signals must both be (B, n_e), got {tuple(reference.shape)} and {tuple(signals.shape)}"
        )
    n = reference.shape[0]
    if k.shape != (n, 8):
        raise ValueError(f"k must be ({n}, 8), got {tuple(k.shape)}")
    if healthy.shape != (n,):
        raise ValueError(f"healthy must be ({n},), got {tuple(healthy.shape)}")
    reference, signals = reference.double(), signals.double()
    spread = (reference.amax(1) - reference.amin(1)).clamp(min=1e-12)
    nrmse = rms(signals - reference) / spread
    dtype = bundle.pod.mean_.dtype
    check = bundle.full_signal_check()
    with torch.no_grad():
        # a noise-aware network is told each record's estimated noise, as the online pipeline does
        found = bundle.diagnose(bundle.compress(signals.to(dtype)), noise=noise_level(signals).to(dtype))
        k_hat = found["k_hat"].double()
        full_flag = check(signals.to(dtype))
        verdict = bundle.verdict_healthy(k_hat)
    gappy_flag = found["out_of_distribution"]
    k = k.double()
    chain = confusion(verdict, healthy)
    return {
        "n": n,
        "nrmse_median": float(nrmse.median()),
        "err_k": err_k(k_hat, k),
        "fdi_mae_max": max(fdi_mae(k_hat, k, weighted=True)),
        "chain_accuracy": chain["accuracy"],
        "chain_missed_fault_rate": chain["missed_fault_rate"],
        "chain_false_alarm_rate": chain["false_alarm_rate"],
        "ood_rate_gappy": float(gappy_flag.double().mean()),
        "ood_rate_full": float(full_flag.double().mean()),
        "ood_rate": float((gappy_flag | full_flag).double().mean()),
    }
