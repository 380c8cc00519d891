"""Boundary refinement of the health classifier (active learning on phi_a): it must put the new labels
where the classifier errs and raise the accuracy, resume from its cache, and refuse bad settings."""

from __future__ import annotations

import pytest
import torch
from surrogate_data import faults, write_store

from phm_torch.apps.train import train_surrogates
from phm_torch.prognostics.damage import DamageModel
from phm_torch.surrogates.classifiers import MLPClassifier
from phm_torch.surrogates.classifiers.damage_paths import POINTS_PER_PATH, DamagePathSampler
from phm_torch.surrogates.classifiers.refinement import BoundaryRefinement, refine_classifier


def phi(k: torch.Tensor) -> torch.Tensor:
    """An analytic stand-in for phi_a: a curved boundary through the crowded corner near k = 0."""
    return (k[:, 0] + 0.7 * k[:, 1] ** 0.5 + 0.4 * k[:, 2] * k[:, 3] + 0.3 * torch.sin(6.0 * k[:, 4])) < 0.45


def importance(n: int, seed: int) -> torch.Tensor:
    """Fault vectors crowding near nominal like the importance sampler's: uniform ** 3."""
    return faults(n, seed) ** 3


class Counting:
    def __init__(self) -> None:
        self.calls = 0
        self.rows = 0

    def __call__(self, k):
        self.calls += 1
        self.rows += len(k)
        return phi(torch.as_tensor(k)).numpy()


def sample(n: int, r: int):
    return importance(n, 100 + r).numpy()


def accuracy(clf: MLPClassifier, k: torch.Tensor) -> float:
    return float((clf.predict(k) == phi(k)).double().mean())


def small_mlp() -> MLPClassifier:
    return MLPClassifier(hidden=[32, 32], epochs=60, batch_size=256, seed=0)


def test_refinement_labels_the_boundary_and_beats_as_many_random_labels(tmp_path):
    k0 = importance(1500, 1)
    settings = BoundaryRefinement(rounds=2, labels_per_round=0.5, candidates_per_label=20)
    assess = Counting()
    clf = small_mlp()
    k_all, h_all, info = refine_classifier(clf, k0, phi(k0), sample, assess, settings, seed=0, cache_dir=tmp_path)
    assert k_all.shape == (1500 + 2 * 750, 8) and h_all.dtype == torch.bool
    assert info["added"] == 1500 and assess.rows == 1500 and info["cached"] == [False, False]
    assert torch.equal(h_all, phi(k_all))  # every new label is phi's
    # the new vectors are the hard ones: the initial classifier is far from perfect on them ...
    assert info["boundary_accuracy"][0] < 0.9
    # ... and both classes are there (importance sampling alone gives mostly one side near the boundary)
    assert 0.2 < info["healthy_fraction"][0] < 0.8
    # against the same number of importance-sampled labels, on fresh importance-sampled vectors
    test = importance(20000, 7)
    k_rand = torch.cat([k0, importance(1500, 2)])
    plain = small_mlp().fit(k_rand, phi(k_rand))
    assert accuracy(clf, test) > accuracy(plain, test) + 0.003
    assert 1 - accuracy(clf, test) < 0.8 * (1 - accuracy(plain, test))  # errors cut by >= 20 %


def test_refinement_resumes_from_its_cache_and_is_deterministic(tmp_path):
    k0 = importance(600, 3)
    settings = BoundaryRefinement(rounds=2, labels_per_round=0.25, candidates_per_label=10)
    first = Counting()
    a = small_mlp()
    k1, h1, _ = refine_classifier(a, k0, phi(k0), sample, first, settings, 0, tmp_path)
    again = Counting()
    b = small_mlp()
    k2, h2, info = refine_classifier(b, k0, phi(k0), sample, again, settings, 0, tmp_path)
    assert again.calls == 0 and info["cached"] == [True, True] and info["assess_s"] == 0.0
    assert torch.equal(k1, k2) and torch.equal(h1, h2)
    assert torch.equal(a.flat_weights, b.flat_weights)
    # another seed is another key: labelled afresh
    c = Counting()
    refine_classifier(small_mlp(), k0, phi(k0), sample, c, settings, 1, tmp_path)
    assert c.calls == 2
    # no rounds: a plain fit
    n = Counting()
    k3, _, info = refine_classifier(small_mlp(), k0, phi(k0), sample, n, BoundaryRefinement(0, 0.25, 10), 0, None)
    assert n.calls == 0 and k3.shape == (600, 8) and info["added"] == 0


DIRECTION = torch.tensor([0.5, 0.3, 0.6, 0.6, 0.2, 0.4, 0.0, 0.1])  # a wear direction (no phase component)


def ray_points(n: int, seed: int) -> torch.Tensor:
    """Points t * d on rays from k = 0 along directions d scattered around ``DIRECTION``: paths of a damage law."""
    g = torch.Generator().manual_seed(seed)
    d = (DIRECTION * (1.0 + 0.3 * torch.randn(n, 8, generator=g, dtype=torch.float64))).clamp(min=0.0)
    t = torch.rand(n, 1, generator=g, dtype=torch.float64)
    return (t * d).clamp(0.0, 1.0)


def crossing_error(clf: MLPClassifier, n: int = 200) -> float:
    """Median |t_classifier - t_phi| of the first healthy -> faulty crossing along n fresh rays."""
    g = torch.Generator().manual_seed(99)
    d = (DIRECTION * (1.0 + 0.3 * torch.randn(n, 8, generator=g, dtype=torch.float64))).clamp(min=0.0)
    t = torch.linspace(0.0, 1.0, 801, dtype=torch.float64)
    k = (t.view(1, -1, 1) * d.view(n, 1, 8)).clamp(0.0, 1.0).reshape(-1, 8)
    truth, said = (~phi(k)).view(n, -1), (~clf.predict(k)).view(n, -1)
    ok = truth.any(1) & said.any(1)
    first = lambda x: t[x.double().argmax(1)]
    return float((first(said[ok]) - first(truth[ok])).abs().median())


def test_path_labels_put_the_boundary_where_the_paths_cross_it():
    """Labels on the paths of a damage law (here rays along a wear direction) move the classifier's crossing of
    phi's boundary along them toward phi's: the RUL's event time, which importance-sampled labels leave loose."""
    k0 = importance(1500, 1)
    assess = Counting()
    plain = small_mlp()
    refine_classifier(plain, k0, phi(k0), sample, assess, BoundaryRefinement(2, 0.5, 20), seed=0)
    on_paths = small_mlp()
    settings = BoundaryRefinement(2, 0.25, 20, path_labels_per_round=0.25)  # the same number of labels
    k_all, h_all, info = refine_classifier(
        on_paths, k0, phi(k0), sample, assess, settings, seed=0, sample_paths=lambda n, r: ray_points(n, 50 + r).numpy()
    )
    assert info["labels_per_round"] == 375 and info["path_labels_per_round"] == 375 and info["added"] == 1500
    assert torch.equal(h_all, phi(k_all)) and len(info["path_boundary_accuracy"]) == 2
    assert crossing_error(on_paths) < 0.7 * crossing_error(plain)  # measured 0.014 against 0.025
    with pytest.raises(ValueError, match="path_labels_per_round=0.25: no damage law"):
        refine_classifier(small_mlp(), k0, phi(k0), sample, assess, settings, seed=0)


def test_damage_path_candidates_start_near_nominal_and_follow_the_law():
    nominal = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]
    rate = torch.diag(torch.tensor([6e-4, 5e-4, 5e-4, 5e-4, 5e-4, 4e-4, 0.0, 3e-4])).tolist()
    law = DamageModel(rate, [0.0] * 8, 250.0, 20000.0, 50.0, nominal)  # no eps, s = 1: deterministic paths
    sampler = DamagePathSampler(law, 0.01, uniform=(6,), seed=3)
    paths = sampler.paths(64, torch.Generator().manual_seed(0))  # (T, 64, 8)
    start, dk = paths[0], paths - torch.tensor(nominal, dtype=torch.float64)
    assert (dk[0, :, [0, 1, 2, 3, 4, 5, 7]].abs() <= 0.01 + 1e-12).all()
    assert start[:, 6].std() > 0.2  # the phase is uniform, and constant along the path
    assert torch.equal(paths[:, :, 6], start[:, 6].expand_as(paths[:, :, 6]))
    # damage only grows away from nominal (F >= 0, no eps), and follows dk(t) = dk(0) exp(F t) (RK4)
    assert (dk.abs().diff(dim=0) >= -1e-12).all()
    t = law.grid[40]
    exact = (dk[0] * torch.exp(torch.diag(torch.tensor(rate, dtype=torch.float64)) * t)).clamp(-1, 1)
    assert torch.allclose(dk[40], exact, atol=1e-6)
    a, b = sampler.sample(1000, 0), sampler.sample(1000, 0)
    assert a.shape == (1000, 8) and (a == b).all() and not (a == sampler.sample(1000, 1)).all()
    assert a.min() >= 0.0 and a.max() <= 1.0 and POINTS_PER_PATH > 1


@pytest.mark.parametrize(
    "field,value",
    [
        ("rounds", -1),
        ("rounds", 1.5),
        ("labels_per_round", 0.0),
        ("labels_per_round", float("nan")),
        ("candidates_per_label", 0),
        ("path_labels_per_round", -0.1),
    ],
)
def test_bad_settings_name_the_field(field, value):
    kwargs = {"rounds": 1, "labels_per_round": 0.5, "candidates_per_label": 10, field: value}
    with pytest.raises(ValueError, match=f"classifier_refine.{field}"):
        BoundaryRefinement(**kwargs)


def test_train_refuses_refinement_on_a_store_without_its_assessment(compose, tmp_path):
    store = write_store(tmp_path / "s", {"train": 60, "val": 20})
    with pytest.raises(ValueError, match=r"classifier_refine.rounds=3: the store .* does not record"):
        train_surrogates(
            compose(
                "train",
                [
                    f"data_dir={store}",
                    f"out_dir={tmp_path / 'o'}",
                    "n_modes=10",
                    "n_points=16",
                    "model.fit.max_epochs=1",
                ],
            )
        )


def test_labels_of_the_same_assessment_are_reused_by_vector_across_keys(tmp_path):
    """phi_a is a function of k: under the same ``labels_of`` a run whose round keys differ (here the seed in the
    key) takes the labels of the vectors the cache already holds and assesses none again; under another identity
    (another store's phi_a) it assesses them all."""
    k0 = importance(600, 3)
    settings = BoundaryRefinement(rounds=2, labels_per_round=0.25, candidates_per_label=10)
    first = Counting()
    k1, h1, _ = refine_classifier(small_mlp(), k0, phi(k0), sample, first, settings, 0, tmp_path, labels_of="store")
    again = Counting()
    k2, h2, info = refine_classifier(small_mlp(), k0, phi(k0), sample, again, settings, 1, tmp_path, labels_of="store")
    assert info["cached"] == [False, False]  # another key ...
    assert again.rows == 0 and info["reused_labels"] == info["added"] == 300  # ... the same vectors' labels
    assert torch.equal(k1, k2) and torch.equal(h1, h2)
    other = Counting()
    _, _, info = refine_classifier(small_mlp(), k0, phi(k0), sample, other, settings, 2, tmp_path, labels_of="another")
    assert other.rows == 300 and info["reused_labels"] == 0
