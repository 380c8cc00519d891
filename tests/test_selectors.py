"""Sample-time selectors: the interface, Q-DEIM = PySensors' QR, greedy oversampling, SOM placement."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
from surrogate_data import faults, signals

from phm_torch.surrogates import POD, GappyPOD, err_alpha
from phm_torch.surrogates.selectors import SELECTORS, GreedySelector, MinErrorSelector, SOMSelector, build_selector


@pytest.fixture(scope="module")
def snapshots() -> torch.Tensor:
    return signals(faults(200, 1), noise=0.01)


@pytest.fixture(scope="module")
def modes(snapshots) -> torch.Tensor:
    return POD(8).fit(snapshots).modes_


def smallest_singular(modes: torch.Tensor, idx: torch.Tensor) -> float:
    return float(torch.linalg.svdvals(modes[idx].double())[-1])


@pytest.mark.parametrize("name", sorted(SELECTORS))
def test_interface(name, modes, snapshots):
    sel = build_selector(name, n_points=20)
    sel.fit(modes, snapshots=snapshots) if sel.needs_snapshots else sel.fit(modes)
    idx = sel.indices_
    assert idx.dtype == torch.long and idx.shape == (20,)
    assert idx.unique().numel() == 20
    assert bool((idx[1:] > idx[:-1]).all())  # increasing (acquisition order)
    assert int(idx.min()) >= 0 and int(idx.max()) < modes.shape[0]
    assert "n_points" in sel.get_params()


def test_qdeim_is_pysensors_qr(modes):
    # PySensors' QR optimizer: _, _, pivots = scipy.linalg.qr(basis.T, pivoting=True); sensors = pivots[:n]
    _, _, piv = scipy.linalg.qr(modes.numpy().T, pivoting=True)
    for n in (5, 8):
        idx = build_selector("qdeim", n_points=n).fit(modes).indices_
        assert idx.tolist() == sorted(piv[:n].tolist())


def test_greedy_oversampling_raises_the_smallest_singular_value(modes):
    qdeim = build_selector("qdeim", n_points=8).fit(modes).indices_
    greedy8 = GreedySelector(8).fit(modes).indices_
    assert greedy8.tolist() == qdeim.tolist()  # below/at n_m it is Q-DEIM
    previous = smallest_singular(modes, greedy8)
    for n in (12, 16, 24):
        idx = GreedySelector(n).fit(modes).indices_
        s = smallest_singular(modes, idx)
        assert s >= previous - 1e-12  # each added point can only raise it
        previous = s
    rand = build_selector("random", n_points=24, seed=3).fit(modes).indices_
    unif = build_selector("uniform", n_points=24).fit(modes).indices_
    assert previous > smallest_singular(modes, rand)
    assert previous > smallest_singular(modes, unif)


def test_d_optimal_maximises_the_determinant_gain(modes):
    idx = GreedySelector(12, criterion="d_optimal").fit(modes).indices_
    det = float(torch.linalg.det(modes[idx].double().T @ modes[idx].double()))
    rand = build_selector("random", n_points=12, seed=0).fit(modes).indices_
    assert det > float(torch.linalg.det(modes[rand].double().T @ modes[rand].double()))


def test_min_error_lowers_the_coefficient_error_of_held_out_signals():
    # Signals = a rank-8 family + a fixed-shape, random-amplitude ripple outside the span (like PWM ripple).
    n_e = 801
    t = torch.linspace(0, 1, n_e, dtype=torch.float64)
    ripple = torch.sin(2 * torch.pi * 90 * t) * (1 + 4 * (t > 0.5))  # strong in the second half

    def family(seed: int) -> torch.Tensor:
        g = torch.Generator().manual_seed(seed)
        base = signals(faults(300, seed), noise=0.0).double()
        return base + torch.randn(300, 1, generator=g, dtype=torch.float64) * ripple

    train, test = family(3), family(4)
    pod = POD(8).fit(train)
    full = pod(test)

    def error(sel) -> float:
        gappy = GappyPOD(pod.modes_, pod.mean_, sel.indices_)
        return float(err_alpha(gappy(gappy.select(test))[0], full).median())

    mine = error(MinErrorSelector(24).fit(pod.modes_, snapshots=train, mean=pod.mean_))
    assert mine < 0.7 * error(GreedySelector(24).fit(pod.modes_))
    assert mine < 0.7 * error(GreedySelector(24, criterion="d_optimal").fit(pod.modes_))
    # At n_points <= n_m it is Q-DEIM.
    assert torch.equal(
        MinErrorSelector(8).fit(pod.modes_, snapshots=train).indices_,
        build_selector("qdeim", n_points=8).fit(pod.modes_).indices_,
    )
    with pytest.raises(ValueError, match="min_error needs the training snapshots"):
        MinErrorSelector(12).fit(pod.modes_)


def test_uniform_and_random():
    m = torch.randn(101, 3, dtype=torch.float64)
    assert build_selector("uniform", n_points=5).fit(m).indices_.tolist() == [0, 25, 50, 75, 100]
    a = build_selector("random", n_points=7, seed=1).fit(m).indices_
    assert torch.equal(a, build_selector("random", n_points=7, seed=1).fit(m).indices_)
    assert not torch.equal(a, build_selector("random", n_points=7, seed=2).fit(m).indices_)


def test_som_puts_points_where_the_modes_vary():
    # Two modes that vary fast in the first fifth of the record and are flat elsewhere.
    n = 1001
    t = torch.linspace(0, 1, n, dtype=torch.float64)
    bump = (t < 0.2).to(torch.float64)
    m = torch.stack([torch.sin(40 * np.pi * t) * bump, torch.cos(40 * np.pi * t) * bump + 0.01], 1)
    idx = SOMSelector(20, time_weight=0.5).fit(m, t).indices_
    early = int((t[idx] < 0.2).sum())
    assert early >= 8  # uniform sampling would put 4 there
    # Deterministic (batch SOM).
    assert torch.equal(idx, SOMSelector(20, time_weight=0.5).fit(m, t).indices_)


def test_som_map_shape_and_scaling(modes):
    idx = SOMSelector(12, map_shape=[3, 4]).fit(modes).indices_
    assert idx.numel() == 12
    with pytest.raises(ValueError, match=r"selector.map_shape \[3, 5\] has 15 neurons but n_points=12"):
        SOMSelector(12, map_shape=[3, 5])
    with pytest.raises(ValueError, match="selector.column_scaling"):
        SOMSelector(12, column_scaling="zscore")
    with pytest.raises(ValueError, match="selector.time_weight"):
        SOMSelector(12, time_weight=-1.0)


def test_bad_input(modes):
    with pytest.raises(ValueError, match="selector: unknown name 'deim'"):
        build_selector("deim", n_points=3)
    with pytest.raises(ValueError, match=r"selector.n_points \(uniform\) must be an integer >= 1"):
        build_selector("uniform", n_points=0)
    with pytest.raises(ValueError, match="exceeds the 801 samples"):
        build_selector("uniform", n_points=900).fit(modes)
    with pytest.raises(ValueError, match="selector.criterion"):
        GreedySelector(10, criterion="a_optimal")
    with pytest.raises(ValueError, match="time must have shape"):
        build_selector("som", n_points=4).fit(modes, torch.zeros(3))


def test_som_exchanges_the_fewest_points_when_its_own_leave_the_gappy_matrix_ill_conditioned(modes, caplog):
    """Above max_condition the fewest of the map's points are exchanged that bring G within the bound (said in the
    log and in fallback_), the rest stay where the map put them; at the default bound the map's own points stay."""
    from phm_torch.surrogates.selectors.exchange import gram_condition

    own = SOMSelector(12, max_condition=None).fit(modes)
    assert own.fallback_ is None and own.condition_ == pytest.approx(gram_condition(modes, own.indices_))
    default = SOMSelector(12).fit(modes)
    assert torch.equal(default.indices_, own.indices_) and default.fallback_ is None and own.condition_ < 1000
    bound = own.condition_ / 3
    with caplog.at_level("WARNING", logger="phm_torch.surrogates.selectors.som"):
        strict = SOMSelector(12, max_condition=bound).fit(modes)
    replaced = int((~torch.isin(strict.indices_, own.indices_)).sum())
    assert 1 <= replaced < 12 and strict.fallback_ == {
        "replaced": replaced,
        "som_condition": pytest.approx(own.condition_),
        "condition": pytest.approx(gram_condition(modes, strict.indices_)),
    }
    assert strict.condition_ <= bound and f"exchanged {replaced} of its points" in caplog.text
    # the fewest: one swap fewer than it made leaves G above the bound
    from phm_torch.surrogates.selectors.exchange import exchange_points

    _, swaps, condition = exchange_points(modes, own.indices_.clone(), bound, max_swaps=replaced - 1)
    assert swaps == replaced - 1 and condition > bound
    assert strict.get_params()["max_condition"] == pytest.approx(bound)
    # a bound no exchange reaches: the greedy E-optimal set where it does better, else the best exchange
    greedy = GreedySelector(12).fit(modes)
    unreachable = SOMSelector(12, max_condition=1.0).fit(modes)
    assert unreachable.condition_ <= min(gram_condition(modes, greedy.indices_), strict.condition_) + 1e-9
    for bad in (0.5, "1e3", True):
        with pytest.raises(ValueError, match="selector.max_condition must be a number >= 1 or null"):
            SOMSelector(12, max_condition=bad)


def test_exchange_points_raises_the_smallest_eigenvalue_and_checks_its_input(modes):
    """Each swap lowers the condition number (the first-order candidate is checked exactly); a set with no more
    points than modes, or a bound below 1, is refused."""
    from phm_torch.surrogates.selectors.exchange import best_swap, exchange_points, gram_condition

    start = torch.arange(0, 12 * 3, 3)  # 12 early, closely spaced samples: a poorly conditioned set
    before = gram_condition(modes, start)
    swapped, (lost, after) = best_swap(modes, start)
    assert lost == 0 and after < before and int((swapped != start).sum()) == 1 and swapped.unique().numel() == 12
    kept, swaps, condition = exchange_points(modes, start, before / 10)
    assert condition <= before / 10 and swaps >= 1 and condition == pytest.approx(gram_condition(modes, kept))
    assert exchange_points(modes, start, before * 2)[1] == 0  # already within: nothing exchanged
    with pytest.raises(ValueError, match="needs more points than modes"):
        exchange_points(modes, torch.arange(8), 10.0)
    with pytest.raises(ValueError, match="max_condition must be >= 1"):
        exchange_points(modes, start, 0.5)


def test_exchange_points_restores_a_rank_deficient_set_one_direction_at_a_time():
    """20 adjacent samples of smooth modes span only a few directions: G's condition number is rounding noise, and no
    single swap lowers it, but each restores one lost direction, so the exchange keeps going until the bound."""
    from phm_torch.surrogates.selectors.exchange import exchange_points, gram_condition

    t = torch.linspace(0.0, 1.0, 2001, dtype=torch.float64)
    modes, _ = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.1 * t + i) for i in range(12)], 1))
    start = torch.arange(20)
    assert gram_condition(modes, start) > 1e12
    kept, swaps, condition = exchange_points(modes, start, 1000.0)
    assert condition <= 1000.0 and swaps >= 5 and condition == pytest.approx(gram_condition(modes, kept))
