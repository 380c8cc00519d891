"""The bounded finite-difference Levenberg-Marquardt (phm_torch/fitting/): analytic minimum, a minimum outside
the bounds, the Laplace covariance against a finite-difference Hessian, and the rows each mode spends."""

from __future__ import annotations

import pytest
import torch

from phm_torch.fitting import Problem, fit, from_residuals

T = torch.linspace(0.0, 1.0, 200, dtype=torch.float64)
SIGMA = 0.01
# The LF fit's settings (phm_torch/lf_fit.py): trials alone, then the Jacobian at the accepted point.
LF_MODE = {
    "lambdas": (0.1, 1.0, 10.0, 100.0),
    "damping": 1e-3,
    "trial_jacobians": False,
    "predicted_stop": False,
    "max_failures": None,
    "max_damping": 1e8,
}


def decay(y: torch.Tensor, rows: list[torch.Tensor] | None = None):
    """Residuals (a exp(-b t) - y) / SIGMA of parameter rows (P, 2); refuses rows outside [0, 10] x [0, 2.5]
    when the bounds below are in force, so that an infeasible probe fails the test."""

    def residuals(x: torch.Tensor) -> torch.Tensor:
        if rows is not None:
            rows.append(x.clone())
        return (x[:, :1] * torch.exp(-x[:, 1:] * T) - y) / SIGMA

    return residuals


def problem(upper_b: float = 10.0, step: float = 1e-6) -> Problem:
    return Problem(
        torch.tensor([1.0, 1.0]), torch.tensor([0.0, 0.0]), torch.tensor([10.0, upper_b]), torch.tensor([step, step])
    )


@pytest.mark.parametrize("mode", [{}, LF_MODE], ids=["trial_jacobians", "lf_mode"])
def test_noise_free_decay_converges_to_the_generating_parameters(mode):
    y = 2.0 * torch.exp(-3.0 * T)
    res = fit(from_residuals(decay(y)), [problem()], max_iter=40, tol_abs=0.0, tol_rel=1e-12, **mode)[0]
    assert res.x.tolist() == pytest.approx([2.0, 3.0], abs=1e-6)
    assert res.cost < 1e-8  # against 0.5 * 200 / 2 ~ 50 for a wrong b
    assert res.history[0] > 1e4 and res.history == sorted(res.history, reverse=True)


@pytest.mark.parametrize("mode", [{}, LF_MODE], ids=["trial_jacobians", "lf_mode"])
def test_minimum_outside_the_bounds_ends_on_the_bound_near_the_conditional_optimum(mode):
    """b is bounded to <= 2.5 below the true 3: b ends on the bound and a near its least-squares value given
    b = 2.5, a* = (y . e) / (e . e) with e = exp(-2.5 t); no probe leaves the box (steps go backwards).

    The steps are clipped to the box (no active set), so along the bound a creeps towards a*: after 30
    iterations the cost is within 0.05 (half chi-square units) of the constrained minimum, i.e. a within
    0.3 standard deviations of a*.
    """
    y = 2.0 * torch.exp(-3.0 * T)
    rows: list[torch.Tensor] = []
    res = fit(
        from_residuals(decay(y, rows)),
        [problem(upper_b=2.5, step=1e-4)],
        max_iter=30,
        tol_abs=0.0,
        tol_rel=1e-10,
        **mode,
    )[0]
    e = torch.exp(-2.5 * T)
    a_star = float(y @ e / (e @ e))
    r_star = (a_star * e - y) / SIGMA
    assert float(res.x[1]) == 2.5
    assert 0.0 <= res.cost - 0.5 * float(r_star @ r_star) < 0.05
    assert float(res.x[0]) == pytest.approx(a_star, rel=1e-3)
    probes = torch.cat(rows)
    assert float(probes[:, 1].max()) <= 2.5 and float(probes.min()) >= 0.0


def test_covariance_is_the_inverse_finite_difference_hessian_at_the_optimum():
    """At the optimum of a noisy fit, s^2 (J^T J)^-1 matches s^2 H^-1 with H the central-difference Hessian
    of 0.5 ||r||^2 (the Gauss-Newton term dominates: residuals are noise, curvature of r is small)."""
    gen = torch.Generator().manual_seed(1)
    y = 2.0 * torch.exp(-3.0 * T) + SIGMA * torch.randn(T.shape, generator=gen, dtype=torch.float64)
    residuals = decay(y)
    res = fit(from_residuals(residuals), [problem()], max_iter=40, tol_abs=1e-9, tol_rel=1e-12)[0]
    assert 0.7 < res.chi2 / (200 - 2) < 1.3  # noise-normalised residual: chi^2 ~ dof

    def cost(x: torch.Tensor) -> float:
        r = residuals(x.unsqueeze(0))[0]
        return 0.5 * float(r @ r)

    h, eye = 1e-4, torch.eye(2, dtype=torch.float64)
    hess = torch.tensor(
        [
            [
                (
                    cost(res.x + h * (eye[i] + eye[j]))
                    - cost(res.x + h * (eye[i] - eye[j]))
                    - cost(res.x - h * (eye[i] - eye[j]))
                    + cost(res.x - h * (eye[i] + eye[j]))
                )
                / (4 * h * h)
                for j in range(2)
            ]
            for i in range(2)
        ],
        dtype=torch.float64,
    )
    expected = res.chi2 / (200 - 2) * torch.linalg.inv(hess)
    assert torch.allclose(res.covariance(), expected, rtol=0.02, atol=0.0)
    # and the fitted values lie within a few standard deviations of the truth
    assert (torch.abs(res.x - torch.tensor([2.0, 3.0], dtype=torch.float64)) < 4 * res.std()).all()


def test_lf_mode_spends_the_trials_alone_then_one_jacobian():
    """trial_jacobians=False: one row per damping multiplier, then n + 1 rows at the accepted point."""
    y = 2.0 * torch.exp(-3.0 * T)
    rows: list[torch.Tensor] = []
    fit(from_residuals(decay(y, rows)), [problem()], max_iter=2, tol_abs=0.0, tol_rel=0.0, **LF_MODE)
    assert [len(r) for r in rows] == [3, 4, 3, 4, 3]  # start Jacobian, (trials, Jacobian) x 2
    rows.clear()
    fit(from_residuals(decay(y, rows)), [problem()], max_iter=2, tol_abs=0.0, tol_rel=0.0)
    assert [len(r) for r in rows] == [3, 9, 9]  # start, then 3 trials x 3 rows per iteration


def test_start_outside_the_bounds_is_refused():
    with pytest.raises(ValueError, match=r"x0\[1\] = 3 is outside its bounds \[0, 2.5\]"):
        Problem(
            torch.tensor([1.0, 3.0]), torch.tensor([0.0, 0.0]), torch.tensor([10.0, 2.5]), torch.tensor([1e-6, 1e-6])
        )
