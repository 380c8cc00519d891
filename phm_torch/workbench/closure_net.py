"""The neural closure's network and the effect that puts it into the simulator.

:class:`ClosureNet` is a random-feature MLP of the state (the features: sin/cos(h theta_m) for mechanical
harmonics h of the rotor angle, the motor speed, the driven-pair current and the surface angle, each scaled to
O(1)); :class:`NeuralClosure` is the :class:`~phm_torch.effects.Effect` whose hook is the network, so the
simulator runs it like any library effect. Fitting and attribution are in :mod:`.closure`; the batched
evaluator (:mod:`.model`) builds the effect too, so the network and its effect sit below both of them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from ..effects import Effect, EffectContext

EQUATIONS = ("torque", "voltage")


class ClosureNet(nn.Module):
    """Random-feature MLP; ``forward(features (B, d), weights (B, n_weights) or (n_weights,)) -> (B,)``.

    Args:
        harmonics: mechanical harmonic orders of theta_m used as inputs.
        hidden: number of hidden tanh units.
        speed_scale [rad/s], current_scale [A], angle_scale [rad]: input normalisers.
        equation: ``torque`` (motor shaft [N m]) or ``voltage`` (driven-pair voltage error [V]).
        output_scale: unit of the output weights [N m] or [V].
        seed: seeds the hidden layer.
    """

    def __init__(
        self,
        harmonics: Sequence[int],
        hidden: int,
        speed_scale: float,
        current_scale: float,
        angle_scale: float,
        equation: str = "torque",
        output_scale: float = 1e-3,
        seed: int = 0,
    ):
        super().__init__()
        if equation not in EQUATIONS:
            raise ValueError(f"closure.equation must be one of {list(EQUATIONS)}, got {equation!r}")
        if not harmonics or any(int(h) != h or h < 1 for h in harmonics):
            raise ValueError(f"closure.harmonics must be positive integers, got {list(harmonics)}")
        if hidden < 0:
            raise ValueError(f"closure.hidden must be >= 0, got {hidden}")
        for name, v in (
            ("speed_scale", speed_scale),
            ("current_scale", current_scale),
            ("angle_scale", angle_scale),
            ("output_scale", output_scale),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"closure.{name} must be > 0, got {v!r}")
        self.harmonics = [int(h) for h in harmonics]
        self.equation, self.output_scale = equation, float(output_scale)
        self.scales = (float(speed_scale), float(current_scale), float(angle_scale))
        d = 2 * len(self.harmonics) + 3
        gen = torch.Generator().manual_seed(int(seed))
        self.register_buffer("w1", torch.randn(hidden, d, generator=gen, dtype=torch.float64) / math.sqrt(d))
        self.register_buffer("b1", 0.5 * torch.randn(hidden, generator=gen, dtype=torch.float64))
        self.n_features, self.hidden = d, int(hidden)
        self.n_weights = 1 + d + self.hidden

    def feature_names(self) -> list[str]:
        names = []
        for h in self.harmonics:
            names += [f"sin({h} theta_m)", f"cos({h} theta_m)"]
        return [*names, "motor speed", "current", "surface angle"]

    def groups(self) -> dict[str, list[int]]:
        """Input groups for attribution: one per harmonic (sin and cos), then speed, current, surface angle."""
        out = {f"theta_m harmonic {h}": [2 * i, 2 * i + 1] for i, h in enumerate(self.harmonics)}
        d = self.n_features
        out.update({"motor speed": [d - 3], "current": [d - 2], "surface angle": [d - 1]})
        return out

    def features(
        self, theta_m: torch.Tensor, omega_m: torch.Tensor, current: torch.Tensor, theta_u: torch.Tensor
    ) -> torch.Tensor:
        """(B,) states -> (B, d) features."""
        cols = []
        for h in self.harmonics:
            cols += [torch.sin(h * theta_m), torch.cos(h * theta_m)]
        ws, cs, us = self.scales
        cols += [omega_m / ws, current / cs, theta_u / us]
        return torch.stack(cols, dim=-1)

    def forward(self, feats: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        d = self.n_features
        out = weights[..., 0] + (feats * weights[..., 1 : 1 + d]).sum(-1)
        if self.hidden:
            # broadcast multiply-sum, not a matmul: a BLAS call per substep on (B, d) x (d, H) costs ~100x
            # more when its threads compete for the cores (measured 1.6 ms vs 30 us on a loaded 2-core host)
            pre = (feats.unsqueeze(-2) * self.w1).sum(-1) + self.b1
            out = out + (torch.tanh(pre) * weights[..., 1 + d :]).sum(-1)
        return out


class NeuralClosure(Effect):
    """The closure as an effect (not registered in the library): per-sample output weights (B, n_weights).

    With ``trace`` a list, the features of sample 0 are appended at every substep (for attribution).
    """

    name = "neural_closure"
    explains = "a learned torque or voltage term of the state, for what no library effect explains"

    def __init__(self, net: ClosureNet, weights: torch.Tensor, trace: list | None = None):
        super().__init__()
        self.net = net
        self.values = {"weights": weights}
        self.trace = trace

    def _output(self, ctx: EffectContext) -> torch.Tensor:
        feats = self.net.features(ctx.theta_m, ctx.omega_m, ctx.current, ctx.theta_u)
        if self.trace is not None:
            self.trace.append(feats[0].detach().clone())
        return self.net.output_scale * self.net(feats, self.values["weights"])

    def motor_torque(self, ctx: EffectContext) -> torch.Tensor | float:
        return self._output(ctx) if self.net.equation == "torque" else 0.0

    def voltage_error(self, ctx: EffectContext) -> torch.Tensor | float:
        return self._output(ctx) if self.net.equation == "voltage" else 0.0
