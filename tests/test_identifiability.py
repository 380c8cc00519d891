"""signal_sensitivity: proportional for a smooth signal, flat for a rough one; bad arguments refused."""

from __future__ import annotations

import pytest
import torch

from phm_torch.surrogates.identifiability import signal_sensitivity

T = torch.linspace(0, 1, 200, dtype=torch.float64)


def linear(k: torch.Tensor) -> torch.Tensor:
    basis = torch.stack([torch.sin((i + 1) * torch.pi * T) for i in range(8)])  # (8, n)
    return k @ basis


def rough(k: torch.Tensor) -> torch.Tensor:
    # a limit cycle whose phase is set by the parameters, as stick-slip or hunting sets it
    phase = 1e4 * k.sum(1, keepdim=True)
    return torch.sin(2 * torch.pi * 20 * T + phase)


def test_linear_signal_changes_in_proportion_to_the_step():
    k = torch.full((5, 8), 0.5, dtype=torch.float64)
    out = signal_sensitivity(linear, k, steps=(1e-3, 1e-2, 1e-1))
    change = out["rms_change"]
    assert change.shape == (5, 3)
    assert torch.allclose(change[:, 1] / change[:, 0], torch.full((5,), 10.0, dtype=torch.float64), rtol=1e-9)
    assert torch.allclose(out["linearity"], torch.ones(5, dtype=torch.float64), rtol=1e-9)
    # the frozen eccentricity phase never moves: a signal of k7 alone does not change
    only_k7 = signal_sensitivity(lambda kk: kk[:, 6:7].expand(-1, 10), k)
    assert float(only_k7["rms_change"].abs().max()) == 0.0


def test_rough_signal_changes_as_much_at_the_smallest_step():
    k = torch.full((5, 8), 0.5, dtype=torch.float64)
    out = signal_sensitivity(rough, k, steps=(1e-3, 1e-1))
    assert float(out["linearity"].min()) > 20.0
    assert float(out["rms_change"][:, 0].median()) > 0.3  # of a unit sine: no usable information


def test_steps_stay_inside_the_unit_box():
    seen = []

    def record(kk: torch.Tensor) -> torch.Tensor:
        seen.append(kk.clone())
        return linear(kk)

    k = torch.zeros(4, 8, dtype=torch.float64)
    k[:, 7] = 1.0
    out = signal_sensitivity(record, k, steps=(1e-2, 1e-1))
    assert float(seen[0].min()) >= 0.0 and float(seen[0].max()) <= 1.0
    moved = seen[0][4:].reshape(2, 4, 8) - k
    assert torch.allclose(moved.norm(dim=-1), torch.tensor([[1e-2] * 4, [1e-1] * 4], dtype=torch.float64))
    assert torch.isfinite(out["linearity"]).all()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"k": torch.zeros(3, 7)}, "k must be"),
        ({"steps": (1e-2,)}, "steps must be"),
        ({"steps": (1e-1, 1e-2)}, "steps must be"),
        ({"frozen": (8,)}, "frozen must be"),
    ],
)
def test_bad_arguments(kwargs, match):
    args = {"k": torch.full((2, 8), 0.5), **kwargs}
    with pytest.raises(ValueError, match=match):
        signal_sensitivity(linear, **args)
