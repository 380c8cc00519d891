"""The FDI's response near nominal: the mean k_hat as a function of the true k, fitted on a life split and
inverted by the tracker.

The measurement model of :mod:`.measurement` reads k_hat = k + e with e centred. Along run-to-failure histories
the pretrained FDI is not centred: it compresses small damages (backlash read at ~0.55 of its growth between 0
and 0.013, eccentricity at ~0.7, the gain drift at ~0.8), and the same curve appears on every life split of the
simulator (docs/prognostics.md, "The FDI's response"). The tracker reads the wear-rate scale s from the growth of
k_hat, so a compressed growth reads s low and the RUL long (+12 % at half of life on the 40 histories).

Here the response is modelled, component by component, as a monotone piecewise-linear h_j with k_hat_j = h_j(k_j)
+ e_j: the means of k_hat_j and k_j in ``n_bins`` quantile bins of k_j (a binned regression of k_hat on k, which
the estimates' own errors do not attenuate, as a regression of k on k_hat would be), made non-decreasing. The
tracker measures h_j^-1(k_hat_j) (slope 1 beyond the fitted range), its interval moved with it. A component whose
estimates do not follow k (overall slope below ``min_slope``: an unidentified one, the eccentricity phase) is left
as it is, and so is one with too few distinct values to bin.

Every response records the pipeline it was fitted for (the file's SHA-256, actuator and command): phm-track
refuses to apply it to another pipeline.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..faults import FAULT_NAMES, N_FAULTS
from ..io.atomic import atomic_open

FORMAT = "phm_torch.fdi_response/1"
PROBE_TOLERANCE = 1e-4  # k units: the same pipeline in another file or format agrees to 1e-5


def probe_k_hat(model: Any) -> list[float]:
    """k_hat (8,) of the POD mean's selected samples through the pipeline ``model``: what identifies the FDI a
    response belongs to, whatever file or format holds it."""
    with torch.no_grad():
        return [float(v) for v in model(model.gappy.mean_hat.unsqueeze(0))[0][0]]


def check_probe(recorded: Mapping[str, Any], model: Any, source: str, what: str, made: str) -> None:
    """Raise ValueError unless the provenance ``recorded`` of a file made for a pipeline (``what`` names the file,
    ``made`` how it was made) holds that pipeline's probe: the k_hat of ``model``'s POD mean (:func:`probe_k_hat`)
    must be the recorded one to 1e-4, whatever file or format holds the pipeline."""
    probe = recorded.get("probe_k_hat")
    if probe is None:
        raise ValueError(f"{what}: records no probe_k_hat, so it cannot be matched to {source}")
    diff = max(abs(a - b) for a, b in zip(probe_k_hat(model), probe))
    if not diff <= PROBE_TOLERANCE:
        raise ValueError(
            f"{what} was {made} for another pipeline ({recorded.get('source', '?')}): the k_hat of its POD mean "
            f"differs by {diff:.3g} from {source}'s"
        )


def read_companion_json(path: str | os.PathLike, fmt: str, what: str) -> dict[str, Any]:
    """The JSON object of a companion file (``what`` names it in errors) whose ``format`` must be ``fmt``."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{what} {path}: cannot read it ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != fmt:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"{what} {path}: not a {fmt} file (format {found!r})")
    return data


@dataclass(frozen=True)
class FDIResponse:
    """Per component j, the knots (true k, mean k_hat) of h_j; an empty tuple leaves component j as measured.

    Attributes:
        knots_true: N_FAULTS tuples of increasing true k values.
        knots_hat: N_FAULTS tuples of the same lengths, strictly increasing mean k_hat at those k.
        pipeline: what it was fitted for (``sha256``, ``actuator``, ``command``) and on (``records``, ``source``).
    """

    knots_true: tuple[tuple[float, ...], ...]
    knots_hat: tuple[tuple[float, ...], ...]
    pipeline: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.knots_true) != N_FAULTS or len(self.knots_hat) != N_FAULTS:
            raise ValueError(f"fdi response: knots for {N_FAULTS} components expected, got {len(self.knots_true)}")
        for j, (kt, kh) in enumerate(zip(self.knots_true, self.knots_hat)):
            name = f"fdi response knots of {FAULT_NAMES[j]}"
            if len(kt) != len(kh) or len(kt) == 1:
                raise ValueError(
                    f"{name}: need equally many (>= 2, or none) true and k_hat knots, got {len(kt)}, {len(kh)}"
                )
            if not (np.all(np.isfinite(kt)) and np.all(np.isfinite(kh))):
                raise ValueError(f"{name}: not finite")
            if np.any(np.diff(kt) <= 0) or np.any(np.diff(kh) <= 0):
                raise ValueError(f"{name}: must be strictly increasing, got {list(kt)} -> {list(kh)}")

    @property
    def corrected(self) -> list[str]:
        """Names of the components the response moves."""
        return [n for n, kt in zip(FAULT_NAMES, self.knots_true) if kt]

    def invert(self, k_hat: torch.Tensor) -> torch.Tensor:
        """h^-1 of estimates k_hat (B, 8): the true k whose mean estimate they are (clamped to [0, 1]); slope 1
        beyond the knots."""
        out = k_hat.clone()
        for j, (kt, kh) in enumerate(zip(self.knots_true, self.knots_hat)):
            if kt:
                out[:, j] = _interp(
                    k_hat[:, j], torch.tensor(kh, dtype=k_hat.dtype), torch.tensor(kt, dtype=k_hat.dtype)
                )
        return out.clamp(0.0, 1.0)

    def correct(
        self, k_hat: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(k, lower, upper) (B, 8) each: the estimates mapped through h^-1 and their intervals moved with them.
        The calibrated widths are those of k_hat around k already (a clamped bound stays at the clamp); dividing
        them by h' as well was tried and tracked no better (docs/prognostics.md)."""
        k = self.invert(k_hat)
        shift = k - k_hat
        return k, (lower + shift).clamp(0.0, 1.0), (upper + shift).clamp(0.0, 1.0)

    def check_for(self, model: Any, source: str) -> None:
        """Raise ValueError unless this response was fitted for the pipeline ``model`` (``source`` names it)."""
        check_probe(self.pipeline, model, source, "fdi response", "fitted")

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "pipeline": dict(self.pipeline),
            "components": {
                n: {"k_true": list(kt), "k_hat": list(kh)}
                for n, kt, kh in zip(FAULT_NAMES, self.knots_true, self.knots_hat)
            },
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the response as JSON, atomically."""
        with atomic_open(Path(path), "w") as fh:
            json.dump(self.to_json(), fh, indent=1)

    @classmethod
    def load(cls, path: str | os.PathLike) -> FDIResponse:
        """Read a response written by :meth:`save` (JSON only)."""
        data = read_companion_json(path, FORMAT, "fdi response")
        comps = data.get("components", {})
        missing = [n for n in FAULT_NAMES if n not in comps]
        if missing:
            raise ValueError(f"fdi response {path}: components {missing} missing")
        return cls(
            tuple(tuple(float(v) for v in comps[n]["k_true"]) for n in FAULT_NAMES),
            tuple(tuple(float(v) for v in comps[n]["k_hat"]) for n in FAULT_NAMES),
            dict(data.get("pipeline", {})),
        )


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear interpolation of (xp, fp) at x, continued with slope 1 beyond both ends."""
    i = torch.searchsorted(xp, x.contiguous()).clamp(1, xp.numel() - 1)
    x0, x1, f0, f1 = xp[i - 1], xp[i], fp[i - 1], fp[i]
    inside = f0 + (x - x0) * (f1 - f0) / (x1 - x0)
    return torch.where(x < xp[0], fp[0] + (x - xp[0]), torch.where(x > xp[-1], fp[-1] + (x - xp[-1]), inside))


RESPONSE_BINS, RESPONSE_MIN_COUNT = 10, 20  # fit_response's defaults: it needs at least their product of pairs


def fit_response(
    k_true: np.ndarray,
    k_hat: np.ndarray,
    n_bins: int = RESPONSE_BINS,
    min_count: int = RESPONSE_MIN_COUNT,
    min_slope: float = 0.5,
    pipeline: Mapping[str, Any] | None = None,
) -> FDIResponse:
    """Fit h on pairs of true fault vectors ``k_true`` (N, 8) and their FDI estimates ``k_hat`` (N, 8).

    Args:
        n_bins: quantile bins of each true component (bins with fewer than ``min_count`` pairs are dropped).
        min_slope: components whose least-squares slope of k_hat on k is below this are left as measured.
        pipeline: provenance kept with the response (:attr:`FDIResponse.pipeline`).
    """
    k_true, k_hat = np.asarray(k_true, dtype=np.float64), np.asarray(k_hat, dtype=np.float64)
    if k_true.ndim != 2 or k_true.shape[1] != N_FAULTS or k_hat.shape != k_true.shape:
        raise ValueError(
            f"fdi response: k_true and k_hat must both be (N, {N_FAULTS}), got {k_true.shape}, {k_hat.shape}"
        )
    if not (np.isfinite(k_true).all() and np.isfinite(k_hat).all()):
        raise ValueError("fdi response: k_true and k_hat must be finite")
    if isinstance(n_bins, bool) or not isinstance(n_bins, int) or n_bins < 2:
        raise ValueError(f"fdi response: n_bins must be an integer >= 2, got {n_bins!r}")
    if k_true.shape[0] < n_bins * min_count:
        raise ValueError(
            f"fdi response: {k_true.shape[0]} pairs are too few for {n_bins} bins of at least {min_count} "
            f"(a life split of a few hundred inspections at least)"
        )
    knots_true, knots_hat = [], []
    for j in range(N_FAULTS):
        kt, kh = _component_knots(k_true[:, j], k_hat[:, j], n_bins, min_count, min_slope)
        knots_true.append(kt)
        knots_hat.append(kh)
    info = {**dict(pipeline or {}), "records": int(k_true.shape[0]), "n_bins": n_bins, "min_slope": min_slope}
    return FDIResponse(tuple(knots_true), tuple(knots_hat), info)


def _component_knots(
    kt: np.ndarray, kh: np.ndarray, n_bins: int, min_count: int, min_slope: float
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    spread = kt.std()
    if spread <= 0 or np.cov(kt, kh)[0, 1] / spread**2 < min_slope:
        return (), ()  # constant, or not identified: the estimate does not follow k
    edges = np.unique(np.quantile(kt, np.linspace(0.0, 1.0, n_bins + 1)))
    which = np.clip(np.searchsorted(edges, kt, side="right") - 1, 0, len(edges) - 2)
    means = [
        (kt[which == b].mean(), kh[which == b].mean()) for b in range(len(edges) - 1) if (which == b).sum() >= min_count
    ]
    if len(means) < 2:
        return (), ()
    x = np.array([m[0] for m in means])
    y = _isotonic(np.array([m[1] for m in means]))
    # strictly increasing for the inversion: ties (pooled bins) keep their first knot
    keep = np.concatenate([[True], np.diff(y) > 1e-9])
    x, y = x[keep], y[keep]
    if len(x) < 2:
        return (), ()
    return tuple(float(v) for v in x), tuple(float(v) for v in y)


def _isotonic(y: np.ndarray) -> np.ndarray:
    """Non-decreasing least-squares fit to equally weighted y (pool adjacent violators)."""
    blocks: list[list[float]] = []  # [sum, count]
    for v in y:
        blocks.append([float(v), 1.0])
        while len(blocks) > 1 and blocks[-2][0] / blocks[-2][1] > blocks[-1][0] / blocks[-1][1]:
            s, c = blocks.pop()
            blocks[-1][0] += s
            blocks[-1][1] += c
    return np.concatenate([np.full(int(c), s / c) for s, c in blocks])


def pairs_from_track(track: Mapping[str, Any], truth: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(k_true (N, 8), k_hat (N, 8)) of the in-distribution inspections of a track (track.json) of a life split
    with its truth (truth.json): the pairs :func:`fit_response` takes (the pipeline's own k_hat, not corrected)."""
    k_true, k_hat = [], []
    for actuator, info in truth.get("actuators", {}).items():
        tracked = track.get("actuators", {}).get(actuator)
        if tracked is None:
            continue
        by_hours = {float(i["hours"]): i for i in tracked["inspections"]}
        for t in info["inspections"]:
            inspection = by_hours.get(float(t["hours"]))
            if inspection is None or inspection["out_of_distribution"]:
                continue
            k_true.append(t["k_true"])
            k_hat.append([inspection["k_hat"][n] for n in FAULT_NAMES])
    return np.array(k_true, dtype=np.float64).reshape(-1, N_FAULTS), np.array(k_hat, dtype=np.float64).reshape(
        -1, N_FAULTS
    )
