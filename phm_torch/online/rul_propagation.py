"""The RUL of an online pipeline: the damage ODE's propagations from a fault vector, stopped by a classifier.

The damage ODE is linear, so its solution on the RUL grid is k(t) = k0 + A(t) (k - k0 + shift) with
A(t) = expm(F t): the propagators are computed once at build time (and checked against the torchdiffeq
integration in the tests), leaving a batched matrix product and classifier calls online. Three propagations
(5/50/95 %) start from k with its damage moved by the calibrated physics deltas, the FDI band (for a measured
k_hat) and, at 95 %, nominal for the components the test command does not identify; each stops where its
classifier turns faulty (the verdict classifier g for a measured k_hat, except at the quantiles where g cannot
cover, the health classifier f for a known k). The event search is straight-line tensor code: the eager
pipeline and the traced :class:`~phm_torch.online.step.OnlineStep` run this one search.

:class:`RULPropagation` is a mixin of :class:`~phm_torch.online.pipeline.OnlinePipeline` (an ``nn.Module``
whose ``classifier`` and ``verdict_classifier`` submodules it scores with); TorchScript compiles its methods as
the pipeline's own.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ..prognostics.damage import DamageModel

SCORE_BLOCK = 4096  # rows per classifier call in the RUL search
# scan intervals of the default event search: 5 scan points + 7 bisections on the 401-point grid, 12 classifier
# rows per trajectory (25-step scan: 17 + 5 = 22). Over the 18,000 propagations of 6,000 paper-store training
# records' estimates and 31,800 of known vectors both searches gave the same RUL (to 3e-4 h): the score turns
# faulty once along a growing trajectory. Only verdict scores of true vectors, which that classifier never saw,
# turned back healthy between scan points (8 of 31,800; 25-step scan: 0).
SCAN_INTERVALS = 4


class RULPropagation:
    """The RUL buffers and methods of an online pipeline (see the module docstring)."""

    def _init_rul(
        self,
        damage: DamageModel,
        deltas: torch.Tensor,
        direction: torch.Tensor,
        rate_scales: torch.Tensor | None,
        fdi_deltas: torch.Tensor | None,
        fdi_direction: torch.Tensor | None,
        coarse: int | None,
        dtype: torch.dtype,
    ) -> None:
        """Register the RUL buffers (arguments as :class:`~phm_torch.online.pipeline.OnlinePipeline`'s)."""
        t = damage.grid
        a, _ = damage.transitions(t)
        self.register_buffer("times", t.to(dtype))
        self.register_buffer("propagators", a.to(dtype))  # (T, 8, 8)
        self.register_buffer("nominal", damage.nominal.to(dtype))
        self.register_buffer("deltas", torch.as_tensor(deltas, dtype=dtype).reshape(3))
        self.register_buffer("direction", torch.as_tensor(direction, dtype=dtype).reshape(8))
        self.register_buffer(
            "rate_scales",
            torch.ones(3, dtype=dtype) if rate_scales is None else torch.as_tensor(rate_scales, dtype=dtype).reshape(3),
        )
        self.register_buffer(
            "fdi_deltas",
            torch.zeros(3, dtype=dtype) if fdi_deltas is None else torch.as_tensor(fdi_deltas, dtype=dtype).reshape(3),
        )
        self.register_buffer(
            "fdi_direction",
            torch.zeros(8, dtype=dtype)
            if fdi_direction is None
            else torch.as_tensor(fdi_direction, dtype=dtype).reshape(8),
        )
        n_t = int(t.shape[0])
        if coarse is not None and (isinstance(coarse, bool) or not isinstance(coarse, int) or coarse < 1):
            raise ValueError(f"online.coarse must be an integer >= 1 or None, got {coarse!r}")
        self.coarse = max(1, -(-(n_t - 1) // SCAN_INTERVALS)) if coarse is None else int(coarse)
        self.score_block = SCORE_BLOCK
        self.bisections = max(0, (self.coarse - 1).bit_length())  # down to one grid step
        coarse_index = list(range(0, n_t, self.coarse))
        coarse_index += [] if coarse_index[-1] == n_t - 1 else [n_t - 1]
        self.register_buffer("coarse_index", torch.tensor(coarse_index, dtype=torch.long))
        self.mixed_stop = False
        self.register_buffer("health_stop_index", torch.zeros(0, dtype=torch.long))
        # the quantiles the verdict classifier stops: derived from health_stop_index (not stored)
        self.register_buffer("verdict_stop_index", torch.arange(3), persistent=False)
        self.register_buffer("unknown_shift", torch.zeros(3, 8, dtype=dtype))
        # zero, added to the states of the crossing's two final scores: it marks them for the AOTInductor lowering,
        # which keeps their classifiers' tanh exact (:data:`~phm_torch.online.aoti_lowering.CROSSING_MARKER`)
        self.register_buffer("crossing_marker", torch.zeros((), dtype=dtype), persistent=False)

    def set_unidentified(self, components: Sequence[int] | None) -> None:
        """The growing components (``direction`` > 0) among ``components`` (indices) start the 95 % propagation
        of a measured k_hat at nominal: the test command does not identify them, so their k_hat is the training
        prior and their true damage may be anything down to none; the upper bound takes the least. The other
        bounds keep k_hat's value (the 5 % bound is already the shorter one)."""
        idx = sorted({int(v) for v in (components or [])})
        if any(not 0 <= v < 8 for v in idx):
            raise ValueError(f"online.unidentified: component indices must be in [0, 7], got {idx}")
        shift = torch.zeros_like(self.unknown_shift)
        for j in idx:
            if float(self.direction[j]) > 0:
                shift[2, j] = -1.0  # |k - k0| <= 1: the moved damage clamps at nominal
        self.unknown_shift.copy_(shift)

    def set_health_stop(self, quantiles: Sequence[int] | None) -> None:
        """Stop the propagations of a *measured* k_hat at these quantiles (0: 5 %, 2: 95 %) by the health
        classifier f instead of the verdict classifier g. The FDI band's shifted starts are hypotheses about
        the true k; where g cannot cover them (it calls even the nominal vector faulty: an FDI that never
        returns a component it cannot identify teaches g nothing about its true value),
        :func:`~phm_torch.online.fdi_band.calibrate_fdi_band` switches that quantile to f."""
        q = sorted({int(v) for v in (quantiles or [])})
        if any(v not in (0, 2) for v in q):
            raise ValueError(f"online.fdi_health_stop: quantiles must be among 0 (5 %) and 2 (95 %), got {q}")
        self.health_stop_index = torch.tensor(q, dtype=torch.long, device=self.times.device)
        self.verdict_stop_index = torch.tensor([v for v in range(3) if v not in q], device=self.times.device)
        self.mixed_stop = len(q) > 0

    def _score_rows(self, k: torch.Tensor, measured: bool, blocked: bool = True) -> torch.Tensor:
        """Score minus threshold (N,) of fault vectors k (N, 8): the verdict classifier's for ``measured``
        (trajectories of an FDI estimate), the health classifier's otherwise. ``blocked``: in blocks of
        ``SCORE_BLOCK`` rows: a batch's trajectories are ~50 rows per record, and a block's hidden activations
        stay in cache (the classifier ran twice as fast so on 200,000 rows, bandwidth-bound otherwise). Blocks
        give the same scores (every row is scored on its own); a traced step scores all rows at once, since a
        data-dependent number of blocks cannot be traced."""
        if not blocked or k.shape[0] <= self.score_block:
            return self._classify(k, measured)
        return torch.cat([self._classify(block, measured) for block in k.split(self.score_block)])

    def _classify(self, k: torch.Tensor, measured: bool) -> torch.Tensor:
        """One block of :meth:`_score_rows` (TorchScript calls each submodule by name), in the dtype of the health
        classifier's score: the two classifiers may differ in dtype (a score's dtype is its classifier's
        threshold's), and the stopping scores of one propagation mix them."""
        dtype = self.classifier.threshold.dtype
        if measured:
            return (self.verdict_classifier(k) - self.verdict_classifier.threshold).to(dtype)
        return (self.classifier(k) - self.classifier.threshold).to(dtype)

    def _stop_scores(self, k: torch.Tensor, measured: bool, blocked: bool) -> torch.Tensor:
        """Stopping score (M, 3) of the three propagations' states k (M, 3, 8): the verdict classifier's for
        ``measured`` except at the quantiles :meth:`set_health_stop` names, the health classifier's otherwise."""
        m = k.shape[0]
        if not (measured and self.mixed_stop):
            return self._score_rows(k.reshape(-1, 8).clamp(0.0, 1.0), measured, blocked).reshape(m, 3)
        # each quantile scored by its own classifier only (the verdict's rows of a health stop would be overwritten)
        score = torch.zeros(m, 3, dtype=self.classifier.threshold.dtype, device=k.device)
        for cols, by_verdict in ((self.health_stop_index, False), (self.verdict_stop_index, True)):
            rows = k.index_select(1, cols).reshape(-1, 8).clamp(0.0, 1.0)
            score = score.index_copy(1, cols, self._score_rows(rows, by_verdict, blocked).reshape(m, cols.shape[0]))
        return score

    def rul(self, k: torch.Tensor, measured: bool = False, blocked: bool = True) -> torch.Tensor:
        """Deterministic RUL 5/50/95 % [h] (B, 3) from fault vectors (B, 8); 0 if already faulty,
        the horizon if still healthy there.

        ``measured``: k is an FDI estimate, so its error band (``fdi_deltas`` x ``fdi_direction``) joins the
        physics band and the verdict classifier stops the propagations (the health classifier at the
        quantiles of :meth:`set_health_stop`); False for a known k (the health classifier stops them). The
        bounds are the shortest / the longest of the three propagations
        (:func:`phm_torch.prognostics.rul.ordered_bounds`). ``blocked`` as :meth:`_score_rows`.
        """
        fdi = self.fdi_deltas if measured else torch.zeros_like(self.fdi_deltas)
        rul = self.propagations(k, fdi, self.fdi_direction, measured, blocked)
        return torch.stack([rul.amin(-1), rul[:, 1], rul.amax(-1)], dim=-1)

    def propagations(
        self,
        k: torch.Tensor,
        fdi_deltas: torch.Tensor,
        fdi_direction: torch.Tensor,
        measured: bool = False,
        blocked: bool = True,
    ) -> torch.Tensor:
        """RUL [h] (B, 3) of the three propagations q, unordered: from k (B, 8) with its damage moved by
        ``deltas[q] direction + fdi_deltas[q] fdi_direction`` (fdi_deltas (3,), fdi_direction (8,)), on a
        wear clock sped up by ``rate_scales[q]``
        (exact for the linear damage ODE: RUL / s), capped at the horizon; ``measured`` as :meth:`rul`."""
        shift = self.deltas.view(3, 1) * self.direction + fdi_deltas.view(3, 1) * fdi_direction
        if measured:
            shift = shift + self.unknown_shift
        rul = self.rul_shifted(k, shift, measured, blocked) / self.rate_scales
        return torch.minimum(rul, self.times[-1])  # a tensor bound: the traced step reads no Python float

    def rul_shifted(
        self, k: torch.Tensor, shift: torch.Tensor, measured: bool = False, blocked: bool = True
    ) -> torch.Tensor:
        """RUL [h] (B, 3) of three noise-free propagations from k (B, 8) with its damage |k - k_nom| moved by
        shift (3, 8), unordered, stopped as :meth:`rul` says for ``measured``.

        The score is evaluated on a coarse grid (``coarse_index``: every ``coarse`` grid steps and the last),
        the first faulty coarse interval is bisected down to one grid step, and the crossing is interpolated
        linearly in that step. Straight-line tensor code (a fixed number of bisections), so that
        :class:`~phm_torch.online.step.OnlineStep` traces this very search.
        """
        b = k.shape[0]
        dev = k - self.nominal
        # the damage |dk| moves by the shift, away from nominal for the two-sided k8, never past nominal
        # (DeterministicRUL.disturbed)
        side = torch.where(dev >= 0, torch.ones_like(dev), -torch.ones_like(dev)).unsqueeze(1)
        magnitude = dev.abs().unsqueeze(1) + shift.to(dev.dtype).unsqueeze(0)
        dk = side * magnitude.clamp(min=0.0)  # (B, 3, 8)
        coarse = self.coarse_index
        traj = self.nominal + torch.einsum("tij,bqj->tbqi", self.propagators[coarse], dk)  # (Tc, B, 3, 8)
        n_c = traj.shape[0]
        # one call for every scan point (a compiled step took 43 us less for one record so, 5 us more per record in a
        # batch of 4,096 than with a call per scan point)
        score = self._stop_scores(traj.reshape(-1, 3, 8), measured, blocked).reshape(n_c, b, 3)
        faulty = score <= 0
        any_faulty = faulty.any(0)
        first = torch.argmax(faulty.to(torch.int64), dim=0)  # (B, 3)
        hi = coarse[first]  # faulty grid index
        prev = (first - 1).clamp(min=0)
        lo = coarse[prev]  # healthy grid index (or 0)
        for _ in range(self.bisections):
            mid = torch.div(lo + hi, 2, rounding_mode="floor")
            states = self.nominal + (self.propagators[mid] @ dk.unsqueeze(-1)).squeeze(-1)  # (B, 3, 8)
            s_mid = self._stop_scores(states, measured, blocked)
            inner = mid > lo
            hi = torch.where((s_mid <= 0) & inner, mid, hi)
            lo = torch.where((s_mid > 0) & inner, mid, lo)
        # the two scores the crossing is interpolated between, scored again from their states: the linear zero of
        # two close scores magnifies their rounding (a short RUL moves by 1e-7 / (s0 - s1) of a grid step), so the
        # AOTInductor lowering keeps these rows' tanh exact (marked by the zero crossing_marker); every other score
        # only decides a side
        ends = torch.stack([lo, hi])  # (2, B, 3)
        end_states = self.nominal + (self.propagators[ends] @ dk.unsqueeze(-1)).squeeze(-1)  # (2, B, 3, 8)
        end_scores = self._stop_scores((end_states + self.crossing_marker).reshape(2 * b, 3, 8), measured, blocked)
        s0, s1 = end_scores.reshape(2, b, 3).unbind(0)
        t0, t1 = self.times[lo], self.times[hi]
        frac = (s0 / (s0 - s1).clamp(min=1e-12)).clamp(0.0, 1.0)  # linear zero
        crossing = torch.where(first > 0, t0 + frac * (t1 - t0), torch.zeros_like(t0))
        return torch.where(any_faulty, crossing, self.times[-1].expand_as(crossing))
