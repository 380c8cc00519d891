"""Boundary refinement of the health classifier (active learning on phi_a): it must put the new labels
where the classifier errs and raise the accuracy, resume from its cache, and refuse bad settings."""

from __future__ import annotations

import pytest
import torch
from surrogate_data import faults, write_store

from phm_torch.apps.train import train_surrogates
from phm_torch.surrogates.classifiers import MLPClassifier
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


@pytest.mark.parametrize(
    "field,value",
    [
        ("rounds", -1),
        ("rounds", 1.5),
        ("labels_per_round", 0.0),
        ("labels_per_round", float("nan")),
        ("candidates_per_label", 0),
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
