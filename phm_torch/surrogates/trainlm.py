"""Levenberg-Marquardt training of a small network's weights (MATLAB ``trainlm``).

Not the parameter fit of the simulators (:mod:`phm_torch.fitting`, bounded, finite-difference Jacobians):
here the Jacobian is exact (autograd) and the unknowns are the unbounded weights of a network.

The performance is the (weighted) mean squared error of the network outputs, perf = mean(w * e^2) over
all N x n_out entries. Each epoch builds the Jacobian J of the weighted residuals sqrt(w) * e with
respect to every weight and bias (``torch.func``: ``vmap`` of ``jacrev`` over the samples, in chunks),
then tries the step dx = -(J^T J + mu I)^-1 J^T e: if perf falls the step is taken and mu *= mu_dec,
otherwise mu *= mu_inc and the step is tried again, until mu > mu_max. Defaults are trainlm's
(mu 1e-3, mu_dec 0.1, mu_inc 10, mu_max 1e10, min_grad 1e-7). Validation-based early stopping
(trainlm's max_fail) is left to the caller (Lightning's EarlyStopping in ``phm-train``).

The weights are handled as one float64 vector for the solve; the model keeps its own dtype.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn
from torch.func import functional_call, jacrev, vmap


@dataclass
class LMStep:
    """Outcome of one epoch: ``perf`` before and after, ``mu`` after, ``grad_norm`` of perf at the start,
    ``accepted`` (a step lowered perf) and ``stop`` (mu > mu_max or grad_norm < min_grad)."""

    perf_before: float
    perf: float
    mu: float
    grad_norm: float
    accepted: bool
    stop: bool


class TrainLM:
    """LM optimiser for ``model``'s parameters, minimising mean(w * (f(x) - y)^2).

    Args:
        model: the network; ``forward_name`` selects the method to fit (e.g. ``preactivation``).
        mu, mu_dec, mu_inc, mu_max: damping and its update factors (trainlm defaults).
        min_grad: stop when the gradient norm of perf falls below this.
        chunk: samples per Jacobian block (memory ~ chunk * n_out * n_params * 8 bytes).
        forward_name: name of the model method mapping a batch of inputs to outputs.
    """

    def __init__(
        self,
        model: nn.Module,
        mu: float = 1e-3,
        mu_dec: float = 0.1,
        mu_inc: float = 10.0,
        mu_max: float = 1e10,
        min_grad: float = 1e-7,
        chunk: int = 1024,
        forward_name: str = "forward",
    ):
        if not (mu > 0 and 0 < mu_dec < 1 < mu_inc and mu_max > mu):
            raise ValueError(
                f"lm: need mu > 0, 0 < mu_dec < 1 < mu_inc, mu_max > mu; got mu={mu}, "
                f"mu_dec={mu_dec}, mu_inc={mu_inc}, mu_max={mu_max}"
            )
        self.model = model
        self.mu, self.mu_dec, self.mu_inc, self.mu_max = float(mu), float(mu_dec), float(mu_inc), float(mu_max)
        self.min_grad = float(min_grad)
        self.chunk = int(chunk)
        self.forward_name = forward_name
        self.names = [n for n, p in model.named_parameters() if p.requires_grad]
        self.shapes = [p.shape for n, p in model.named_parameters() if p.requires_grad]
        self.sizes = [math.prod(s) for s in self.shapes]
        self._buffers: dict[str, torch.Tensor] = {}

    @property
    def n_params(self) -> int:
        return sum(self.sizes)

    def _flat(self) -> torch.Tensor:
        params = dict(self.model.named_parameters())
        return torch.cat([params[n].detach().to(torch.float64).reshape(-1) for n in self.names])

    def _unflat(self, flat: torch.Tensor) -> dict[str, torch.Tensor]:
        return {n: c.reshape(s) for n, c, s in zip(self.names, flat.split(self.sizes), self.shapes)}

    def _apply(self, flat: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        params = {**self._buffers, **self._unflat(flat)}
        fn: Callable[..., torch.Tensor] = getattr(self.model, self.forward_name)
        if self.forward_name == "forward":
            return functional_call(self.model, params, (x,))
        # functional_call only routes forward; bind the named method through a tiny wrapper.
        return functional_call(_Method(self.model, fn.__name__), {f"m.{k}": v for k, v in params.items()}, (x,))

    def perf(self, flat: torch.Tensor, x: torch.Tensor, y: torch.Tensor, w: torch.Tensor) -> float:
        """mean(w * (f(x) - y)^2) with the weights ``flat`` (float64 inputs)."""
        if not self._buffers:
            self._buffers = {k: v.to(torch.float64) for k, v in self.model.named_buffers()}
        return float((w * (self._apply(flat, x) - y).pow(2)).mean())

    def _normal_equations(
        self, flat: torch.Tensor, x: torch.Tensor, y: torch.Tensor, w: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, float]:
        """J^T J (P, P), J^T e (P,) of the weighted residuals and perf at ``flat``."""
        p = flat.numel()
        jtj = torch.zeros(p, p, dtype=torch.float64, device=flat.device)
        jte = torch.zeros(p, dtype=torch.float64, device=flat.device)
        sse = 0.0

        def single(fl: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
            return self._apply(fl, xi.unsqueeze(0)).squeeze(0)

        jac_fn = vmap(jacrev(single), in_dims=(None, 0))
        for xs, ys, ws in zip(x.split(self.chunk), y.split(self.chunk), w.split(self.chunk)):
            sw = ws.sqrt()
            e = (self._apply(flat, xs) - ys) * sw  # (c, n_out)
            jac = (jac_fn(flat, xs) * sw.unsqueeze(-1)).reshape(-1, p)  # (c * n_out, P)
            jtj += jac.T @ jac
            jte += jac.T @ e.reshape(-1)
            sse += float(e.pow(2).sum())
        return jtj, jte, sse / y.numel()

    @torch.no_grad()
    def step(self, x: torch.Tensor, y: torch.Tensor, w: torch.Tensor | None = None) -> LMStep:
        """One LM epoch on the full data set: x (N, n_in), y (N, n_out), w (N, n_out) weights (default 1)."""
        x, y = x.to(torch.float64), y.to(torch.float64)
        w = torch.ones_like(y) if w is None else w.to(torch.float64)
        self._buffers = {k: v.to(torch.float64) for k, v in self.model.named_buffers()}  # e.g. input scaling
        flat = self._flat()
        with torch.enable_grad():
            jtj, jte, perf0 = self._normal_equations(flat, x, y, w)
        grad_norm = float(2.0 * jte.norm() / y.numel())
        if grad_norm < self.min_grad:
            return LMStep(perf0, perf0, self.mu, grad_norm, False, True)
        eye = torch.eye(jtj.shape[0], dtype=torch.float64, device=jtj.device)
        while self.mu <= self.mu_max:
            try:
                dx = torch.linalg.solve(jtj + self.mu * eye, -jte)
            except RuntimeError:  # singular at tiny mu: damp more
                self.mu *= self.mu_inc
                continue
            cand = flat + dx
            perf = self.perf(cand, x, y, w)
            if math.isfinite(perf) and perf < perf0:
                self.mu = max(self.mu * self.mu_dec, 1e-20)
                self._load(cand)
                return LMStep(perf0, perf, self.mu, grad_norm, True, False)
            self.mu *= self.mu_inc
        return LMStep(perf0, perf0, self.mu, grad_norm, False, True)

    def _load(self, flat: torch.Tensor) -> None:
        params = dict(self.model.named_parameters())
        for n, v in self._unflat(flat).items():
            params[n].data.copy_(v.to(params[n].dtype))

    def fit(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        w: torch.Tensor | None = None,
        epochs: int = 1000,
        x_val: torch.Tensor | None = None,
        y_val: torch.Tensor | None = None,
        w_val: torch.Tensor | None = None,
        max_fail: int = 6,
    ) -> list[dict[str, float]]:
        """Plain trainlm loop (no Lightning): epochs, min_grad, mu_max and max_fail validation stops; the
        weights of the best validation epoch are restored. Returns the per-epoch history."""
        history: list[dict[str, float]] = []
        best, best_val, fails = self._flat(), math.inf, 0
        for epoch in range(epochs):
            out = self.step(x, y, w)
            rec = {"epoch": epoch, "perf": out.perf, "mu": out.mu, "grad_norm": out.grad_norm}
            if x_val is not None and y_val is not None:
                wv = torch.ones_like(y_val, dtype=torch.float64) if w_val is None else w_val.to(torch.float64)
                val = self.perf(self._flat(), x_val.to(torch.float64), y_val.to(torch.float64), wv)
                rec["val_perf"] = val
                if val < best_val:
                    best, best_val, fails = self._flat(), val, 0
                else:
                    fails += 1
            history.append(rec)
            if out.stop or fails >= max_fail:
                break
        if x_val is not None and y_val is not None:
            self._load(best)
        return history


class _Method(nn.Module):
    """Wraps ``module`` so that ``forward`` calls one of its other methods (for ``functional_call``)."""

    def __init__(self, module: nn.Module, method: str):
        super().__init__()
        self.m = module
        self.method = method

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return getattr(self.m, self.method)(x)
