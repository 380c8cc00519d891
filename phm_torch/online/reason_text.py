"""One line for each reason a record is refused (``ood_reasons``), for the ``messages`` of phm-predict and phm-track.

The checks with measured values of their own (``command``, ``tracking``, ``bench``, ``timing``) write their line where
they fire (:mod:`.input_contract`, :mod:`.bench_check`, :mod:`.timing_check`); every other reason gets its line here, so a refused record always says
why in words, not only by name.
"""

from __future__ import annotations

from collections.abc import Sequence

REASON_TEXT = {
    "missing": "too many of the selected samples are missing (NaN) for the gappy least squares",
    "flat": "the record is flat: there is no response to the test command to read",
    "gappy_residual": "the selected samples lie off what the training records' POD modes span (gappy residual above "
    "its limit at this noise)",
    "pod_residual": "the whole record lies off the training records' POD basis (full-record residual above its limit)",
    "roughness": "the record is rougher from sample to sample than any training record (noise, spikes or aliasing)",
    "plateau": "the current holds its extreme value over a stretch (clipping or saturation)",
    "inconsistent": "the FDI's own answer does not reproduce the record (analysis by synthesis: the forward "
    "surrogate's record of k_hat is too far from it)",
    "pipeline": "the pipeline's own out-of-distribution flag",
    "noise": "the estimated noise is above the highest level the intervals were calibrated at",
    "overcurrent": "the current exceeds the drive range the FDI was trained within (a protected drive would have "
    "tripped, or a probe is scaled wrong)",
    "sign": "the mean current has the other sign than the nominal record's while its shape follows it",
    "stuck": "the current holds one exact value over a stretch while it moves elsewhere (a stuck sensor, a burst "
    "of zeros)",
    "gap": "a stretch of the record is missing (a logger's dropout)",
    "held": "the data look decimated and held (runs of equal samples, the changes on a fixed stride)",
    "offset": "over the rest window the current sits off the nominal record (a probe's offset)",
    "unexplained": "for an answer near nominal, more of the record is left unexplained than the model's floor and "
    "the record's white noise allow (coloured noise, hum, an unmodelled effect)",
    "shape": "for an answer without large faults, the record does not look like the nominal record (correlation "
    "below the calibrated threshold)",
    "spikes": "single-sample spikes far above the record's noise and the current's own steps (EMI, switching)",
}
SELF_EXPLAINED = ("command", "tracking", "bench", "timing")  # they write their own line, with their measured values


def reason_lines(reasons: Sequence[str]) -> list[str]:
    """``"<reason>: <what it means>"`` for each reason without a line of its own (:data:`SELF_EXPLAINED`)."""
    return [f"{r}: {REASON_TEXT[r]}" for r in reasons if r not in SELF_EXPLAINED and r in REASON_TEXT]
