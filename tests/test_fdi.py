"""FDI network, its Levenberg-Marquardt trainer, the Lightning module (Adam, LM, end to end), metrics."""

from __future__ import annotations

import itertools
import math

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset

from phm_torch.surrogates import (
    FDIMLP,
    POD,
    GappyPOD,
    SignalAugment,
    TrainLM,
    add_noise,
    err_alpha,
    err_k,
    err_k_interval,
    err_k_weights,
    fdi_mae,
    rms,
)
from phm_torch.surrogates.fdi_ensemble import build_fdi_network
from phm_torch.surrogates.lightning_fdi import FDIModule, KeepBest
from phm_torch.surrogates.selectors import build_selector

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose


def teacher_data(n: int, seed: int, n_in: int = 6) -> tuple[torch.Tensor, torch.Tensor]:
    """Inputs (n, n_in) and targets (n, 8) in [0.05, 0.95] from a random network of the same form."""
    g = torch.Generator().manual_seed(seed)
    w1, w2 = (
        torch.randn(n_in, 12, generator=torch.Generator().manual_seed(99)),
        torch.randn(12, 8, generator=torch.Generator().manual_seed(98)),
    )
    x = torch.randn(n, n_in, generator=g)
    y = 0.5 + 0.45 * torch.tanh(torch.tanh(x @ w1 / 2) @ w2 / 3)
    return x, y


def test_network_form():
    net = FDIMLP(4, 7)
    x = torch.randn(50, 4) * 10
    net.set_normalization(x)
    z = (x - net.in_center) / net.in_scale
    assert float(z.min()) == pytest.approx(-1.0) and float(z.max()) == pytest.approx(1.0)  # mapminmax
    h = 2 / (1 + torch.exp(-2 * net.hidden(z))) - 1  # tansig
    pre = net.output(h)
    assert torch.allclose(net.preactivation(x), pre, atol=1e-5)
    out = net(x * 100)
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0  # satlin
    with pytest.raises(ValueError, match="fdi.n_hidden must be a positive integer"):
        FDIMLP(4, 0)
    with pytest.raises(ValueError, match="fdi.n_layers must be a positive integer, got 0"):
        FDIMLP(4, 7, n_layers=0)


def test_deeper_network_form_and_torchscript():
    torch.manual_seed(0)
    net = FDIMLP(4, 7, n_layers=3)
    x = torch.randn(50, 4)
    net.set_normalization(x)
    z = (x - net.in_center) / net.in_scale
    h = torch.tanh(net.hidden(z))
    for layer in net.deeper:
        h = torch.tanh(layer(h))
    assert len(net.deeper) == 2 and torch.allclose(net.preactivation(x), net.output(h), atol=1e-6)
    scripted = torch.jit.script(net)
    assert torch.equal(scripted(x), net(x))
    # a one-layer state dict (the paper's network, older bundles) has the same keys as before the option
    assert set(FDIMLP(4, 7).state_dict()) == {
        "hidden.weight",
        "hidden.bias",
        "output.weight",
        "output.bias",
        "in_center",
        "in_scale",
    }


def test_ensemble_is_the_mean_of_independently_fitted_members():
    from phm_torch.surrogates import FDIEnsemble

    torch.manual_seed(0)
    x, y = teacher_data(64, 0)
    ens = build_fdi_network(6, 5, n_layers=2, n_members=3, input_scaling="robust").set_normalization(x)
    assert isinstance(ens, FDIEnsemble) and isinstance(build_fdi_network(6, 5), FDIMLP)
    # each member is the FDIMLP with its slice of the stacked weights
    outputs = []
    for i in range(3):
        net = FDIMLP(6, 5, n_layers=2, input_scaling="robust").set_normalization(x)
        with torch.no_grad():
            net.hidden.weight.copy_(ens.w_in[i].T), net.hidden.bias.copy_(ens.b_in[i, 0])
            net.deeper[0].weight.copy_(ens.w_deep[0, i].T), net.deeper[0].bias.copy_(ens.b_deep[0, i, 0])
            net.output.weight.copy_(ens.w_out[i].T), net.output.bias.copy_(ens.b_out[i, 0])
        assert torch.allclose(ens.member_preactivations(x)[i], net.preactivation(x), atol=1e-5)
        outputs.append(net(x))
    assert torch.allclose(ens(x), torch.stack(outputs).mean(0), atol=1e-6)
    assert torch.equal(torch.jit.script(ens)(x), ens(x))
    # FDIModule's loss gives each member the gradient of its own loss: member 1's does not see member 0
    module = FDIModule(ens)

    def member_1_gradient() -> torch.Tensor:
        ens.zero_grad()
        module.training_step((x, y), 0).backward()
        return ens.w_in.grad[1].clone()

    before = member_1_gradient()
    with torch.no_grad():
        ens.w_in[0] += 1.0
    assert torch.equal(member_1_gradient(), before)
    with pytest.raises(ValueError, match="n_members of an ensemble must be an integer >= 2, got 1"):
        FDIEnsemble(6, 5, n_members=1)
    with pytest.raises(ValueError, match="fdi.n_layers must be a positive integer, got 0"):
        FDIEnsemble(6, 5, n_layers=0)
    with pytest.raises(ValueError, match="n_members=3: an ensemble trains with model.optimizer=adam"):
        FDIModule(ens, optimizer="lm")


@pytest.mark.parametrize("n_layers", [1, 2])
def test_lm_normal_equations_match_autograd_jacobian(n_layers):
    torch.manual_seed(0)
    net = FDIMLP(3, 4, n_layers=n_layers).double()
    x, y = torch.randn(5, 3, dtype=torch.float64), torch.rand(5, 8, dtype=torch.float64)
    w = torch.rand(5, 8, dtype=torch.float64)
    lm = TrainLM(net, forward_name="preactivation", chunk=2)
    lm._buffers = {k: v for k, v in net.named_buffers()}
    flat = lm._flat()
    jtj, jte, perf = lm._normal_equations(flat, x, y, w)

    def residual(p: torch.Tensor) -> torch.Tensor:
        return ((lm._apply(p, x) - y) * w.sqrt()).reshape(-1)

    jac = torch.autograd.functional.jacobian(residual, flat)
    e = residual(flat)
    assert torch.allclose(jtj, jac.T @ jac, atol=1e-10)
    assert torch.allclose(jte, jac.T @ e, atol=1e-10)
    assert perf == pytest.approx(float((e**2).mean()))


def test_lm_fits_a_teacher_network_quickly():
    x, y = teacher_data(400, 0)
    xv, yv = teacher_data(100, 1)
    torch.manual_seed(0)
    net = FDIMLP(6, 12).set_normalization(x)
    lm = TrainLM(net, forward_name="preactivation")
    history = lm.fit(x, y, epochs=40, x_val=xv, y_val=yv)
    perfs = [h["perf"] for h in history]
    assert all(b <= a for a, b in itertools.pairwise(perfs))  # LM only takes descending steps
    assert perfs[-1] < 1e-2 * perfs[0]
    assert float((net(xv) - yv).pow(2).mean()) < 2e-3


def _fit(
    module: FDIModule, train: TensorDataset, val: TensorDataset, epochs: int, batch: int | None, tmp_path
) -> tuple[L.Trainer, KeepBest]:
    keep = KeepBest()
    trainer = L.Trainer(
        max_epochs=epochs,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[keep],
        default_root_dir=tmp_path,
        accelerator="cpu",
    )
    trainer.fit(
        module,
        DataLoader(train, batch_size=batch or len(train), shuffle=batch is not None),
        DataLoader(val, batch_size=len(val)),
    )
    return trainer, keep


@pytest.mark.parametrize("optimizer,epochs,batch", [("adam", 40, 64), ("lm", 15, None)])
def test_lightning_module_trains(optimizer, epochs, batch, tmp_path):
    x, y = teacher_data(400, 0)
    xv, yv = teacher_data(100, 1)
    torch.manual_seed(0)
    net = FDIMLP(6, 12).set_normalization(x)
    before = err_k(net(xv), yv)
    module = FDIModule(net, optimizer=optimizer, lr=1e-2)
    _trainer, keep = _fit(module, TensorDataset(x, y), TensorDataset(xv, yv), epochs, batch, tmp_path)
    keep.restore(module)
    after = err_k(module.network(xv), yv)
    assert after < 0.3 * before
    assert keep.best == pytest.approx(after, rel=1e-4)


def test_end_to_end_with_noise_and_missing_samples(tmp_path):
    from surrogate_data import faults, signals

    k, kv = faults(300, 0).float(), faults(80, 1).float()
    y, yv = signals(k), signals(kv)
    pod = POD(10).fit(y)
    gappy = GappyPOD(pod.modes_, pod.mean_, build_selector("greedy", n_points=20).fit(pod.modes_).indices_)
    s, sv = gappy.select(y), gappy.select(yv)
    scale, scale_v = y.pow(2).mean(-1).sqrt(), yv.pow(2).mean(-1).sqrt()
    torch.manual_seed(0)
    net = FDIMLP(10, 16).set_normalization(gappy(s)[0])
    before = err_k(net(gappy(sv)[0]), kv)
    module = FDIModule(net, lr=1e-2, gappy=gappy, augment=SignalAugment(noise=0.01, max_missing=3))
    _, keep = _fit(module, TensorDataset(s, k, scale), TensorDataset(sv, kv, scale_v), 30, 32, tmp_path)
    keep.restore(module)
    assert err_k(module.network(gappy(sv)[0]), kv) < 0.5 * before
    # A training batch really carries NaNs through the gappy layer, with finite gradients.
    torch.manual_seed(1)
    corrupted = module.augment(s[:32], scale[:32])
    assert 0 < int(corrupted.isnan().sum()) <= 3 * 32
    alpha, _ = gappy(corrupted)
    loss = (module.network.preactivation(alpha) - k[:32]).pow(2).mean()
    loss.backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in module.network.parameters())


def test_a_shifting_augment_reads_each_record_moved_by_its_own_shift_within_the_bound():
    records = torch.arange(5 * 100, dtype=torch.float64).reshape(5, 100)  # record r, sample i: 100 r + i
    indices = torch.tensor([0, 10, 50, 99])
    torch.manual_seed(0)
    samples = SignalAugment(noise=0.0, max_missing=0, max_shift=3).select(records, indices)
    shift = samples[:, 1] - records[:, 10]  # the one shift of each record
    assert (shift.abs() <= 3).all() and shift.unique().numel() > 1
    held = (indices.double() + shift.unsqueeze(1)).clamp(0, 99)  # the ends held, as a trigger offset leaves them
    torch.testing.assert_close(samples, records[:, :1] + held)
    with pytest.raises(ValueError, match="model.augment.max_shift must be an integer >= 0"):
        SignalAugment(max_shift=-1)
    # the module takes full records and selects their samples: shifted in training, on time otherwise
    gappy = GappyPOD(torch.linalg.qr(torch.randn(100, 4))[0], torch.zeros(100), indices)
    module = FDIModule(FDIMLP(4, 5), gappy=gappy, augment=SignalAugment(noise=0.0, max_missing=0, max_shift=3))
    batch = (records.float(), torch.zeros(5, 8), torch.ones(5))
    on_time, _, _ = module._inputs(batch, train=False)
    torch.testing.assert_close(on_time, gappy(gappy.select(records.float()))[0])
    torch.manual_seed(1)
    moved, _, _ = module._inputs(batch, train=True)
    assert not torch.allclose(moved, on_time)


def test_module_configuration_errors():
    net = FDIMLP(10, 5)
    with pytest.raises(ValueError, match="model.optimizer must be one of"):
        FDIModule(net, optimizer="sgd")
    with pytest.raises(ValueError, match="model.augment needs the gappy layer"):
        FDIModule(net, augment=SignalAugment())
    gappy = GappyPOD(torch.eye(20)[:, :10], torch.zeros(20))
    with pytest.raises(ValueError, match="model.end_to_end needs model.optimizer=adam"):
        FDIModule(net, optimizer="lm", gappy=gappy)


def test_checkpoint_from_another_configuration():
    small = FDIModule(FDIMLP(10, 5))
    other = FDIModule(FDIMLP(10, 7))
    ckpt = {"hyper_parameters": dict(small.hparams), "state_dict": small.state_dict()}
    with pytest.raises(ValueError, match="checkpoint from another configuration: n_hidden=5 in the checkpoint vs 7"):
        other.on_load_checkpoint(ckpt)
    deeper = FDIModule(FDIMLP(10, 5, n_layers=2))
    old = {k: v for k, v in ckpt["hyper_parameters"].items() if k != "n_layers"}  # before the option
    small.on_load_checkpoint({**ckpt, "hyper_parameters": old})
    with pytest.raises(ValueError, match="n_layers=1 in the checkpoint vs 2 now"):
        deeper.on_load_checkpoint({**ckpt, "hyper_parameters": old})


def test_err_k_as_the_paper_defines_it():
    k_act = torch.zeros(2, 8)
    k_act[:, 5] = torch.tensor([0.0, 0.5])  # eccentricity k6
    k_est = k_act.clone()
    k_est[:, 6] += 0.4  # phase error 0.4 on both signals
    k_est[0, 0] += 0.2  # friction error on the first
    w = err_k_weights(k_act)
    assert w[:, 6].tolist() == [0.0, 0.5] and float(w[:, :6].min()) == 1.0 and float(w[:, 7].min()) == 1.0
    # sqrt(mean over 2 x 8 entries of w (dk)^2) = sqrt((0.2^2 + 0.5 * 0.4^2) / 16)
    assert err_k(k_est, k_act) == pytest.approx(math.sqrt((0.04 + 0.08) / 16))
    assert fdi_mae(k_est, k_act)[6] == pytest.approx(0.4)
    assert fdi_mae(k_est, k_act, weighted=True)[6] == pytest.approx(0.1)


def test_err_k_interval_brackets_err_k_and_narrows_with_more_signals():
    g = torch.Generator().manual_seed(3)

    def case(n: int) -> tuple[torch.Tensor, torch.Tensor]:
        k_act = torch.rand(n, 8, generator=g, dtype=torch.float64)
        # heavy-tailed errors, as in the FDI: a few signals carry most of the squared error
        scale = torch.where(torch.rand(n, 1, generator=g, dtype=torch.float64) < 0.07, 0.15, 0.02)
        return k_act + scale * torch.randn(n, 8, generator=g, dtype=torch.float64), k_act

    small, large = case(500), case(8000)
    lo, hi = err_k_interval(*small)
    assert lo < err_k(*small) < hi
    lo_l, hi_l = err_k_interval(*large)
    assert lo_l < err_k(*large) < hi_l
    assert hi_l - lo_l < 0.5 * (hi - lo)  # width ~ 1 / sqrt(n): a quarter at 16x the signals
    assert err_k_interval(*small, seed=5) != (lo, hi) and err_k_interval(*small) == (lo, hi)
    exact = torch.zeros(50, 8, dtype=torch.float64)  # every signal alike: the interval closes
    value = err_k(exact + 0.1, exact)  # sqrt(7 / 8) x 0.1: no eccentricity, no phase weight
    assert err_k_interval(exact + 0.1, exact) == pytest.approx((value, value))
    nan = small[0].clone()
    nan[0] = float("nan")  # a singular gappy system: left out
    assert all(math.isfinite(v) for v in err_k_interval(nan, small[1]))
    with pytest.raises(ValueError, match="level"):
        err_k_interval(*small, level=1.5)
    with pytest.raises(ValueError, match="n_boot"):
        err_k_interval(*small, n_boot=2)


def test_err_k_by_fault_count_splits_the_paper_err_k():
    from phm_torch.surrogates.metrics import err_k_by_fault_count

    g = torch.Generator().manual_seed(0)
    k_act = torch.rand(400, 8, generator=g, dtype=torch.float64) ** 3
    k_est = (k_act + 0.05 * torch.randn(400, 8, generator=g, dtype=torch.float64)).clamp(0, 1)
    k_act[0] = torch.tensor([0.9, 0.9, 0.9, 0.0, 0.0, 0.0, 0.9, 0.0])  # 3 large, k7 not counted
    k_act[1] = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.9, 0.31])  # 1 large
    groups = err_k_by_fault_count(k_est, k_act)
    assert list(groups) == ["0", "1", "2", "3+"]
    assert sum(v["n"] for v in groups.values()) == 400
    assert sum(v["share_of_squared_error"] for v in groups.values()) == pytest.approx(1.0)
    # the groups recombine into the paper's err_k
    total = sum(v["n"] * v["err_k"] ** 2 for v in groups.values() if v["n"]) / 400
    assert math.sqrt(total) == pytest.approx(err_k(k_est, k_act))
    alone = err_k_by_fault_count(k_est[:2], k_act[:2])
    assert (alone["3+"]["n"], alone["1"]["n"], alone["0"]["n"]) == (1, 1, 0) and math.isnan(alone["0"]["err_k"])
    assert alone["3+"]["err_k"] == pytest.approx(err_k(k_est[:1], k_act[:1]))
    # measured from the healthy vector: k8 = 0.5 is no damage, k8 = 0.1 is (a gain drift below nominal)
    nominal = torch.tensor([0, 0, 0, 0, 0, 0, 0.5, 0.5], dtype=torch.float64)
    k_act[1, 7], k_act[2] = 0.5, torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.1])
    drift = err_k_by_fault_count(k_est[:3], k_act[:3], nominal)
    assert (drift["3+"]["n"], drift["1"]["n"], drift["0"]["n"]) == (1, 1, 1)


def test_err_alpha():
    full = torch.tensor([[0.0, 1.0, 2.0, 4.0]])
    gappy = full + torch.tensor([[0.1, -0.1, 0.1, -0.1]])
    assert float(err_alpha(gappy, full)[0]) == pytest.approx(0.1 / 4.0)


def test_noise_aware_network_takes_the_level_as_one_more_input():
    torch.manual_seed(0)
    x, levels = torch.randn(200, 6), torch.rand(200) * 0.1
    for net in (
        FDIMLP(6, 5, n_layers=2, input_scaling="robust", noise_input=True, default_noise=0.01, max_noise=0.1),
        build_fdi_network(6, 5, 2, 3, input_scaling="robust", noise_input=True, default_noise=0.01, max_noise=0.1),
    ):
        with pytest.raises(ValueError, match="needs the training noise levels"):
            net.set_normalization(x)
        net.set_normalization(x, levels)
        assert net.in_center.shape == (7,)  # the level is scaled like a coefficient
        quiet, loud = net(x, torch.zeros(200)), net(x, torch.full((200,), 0.08))
        assert float((quiet - loud).abs().max()) > 1e-3
        torch.testing.assert_close(net(x), net(x, torch.full((200,), 0.01)))  # None: default_noise
        torch.testing.assert_close(net(x, torch.full((200,), 0.5)), net(x, torch.full((200,), 0.1)))  # held
        scripted = torch.jit.script(net)
        torch.testing.assert_close(scripted(x, levels), net(x, levels))
        torch.testing.assert_close(scripted(x), net(x))
    plain = FDIMLP(6, 5).set_normalization(x)
    torch.testing.assert_close(plain(x, levels), plain(x))  # a plain network ignores the level
    assert "noise_input" not in "".join(plain.state_dict())  # and its state dict is unchanged
    for kwargs, match in (
        ({"noise_input": "yes"}, "fdi.noise_input must be true or false"),
        ({"noise_input": True, "max_noise": 0.0}, "fdi.max_noise must be > 0"),
        (
            {"noise_input": True, "default_noise": 0.2, "max_noise": 0.1},
            r"fdi.default_noise must be in \[0, max_noise=0.1\], got 0.2",
        ),
    ):
        with pytest.raises(ValueError, match=match):
            FDIMLP(6, 5, **kwargs)
    with pytest.raises(ValueError, match="noise_input=true needs noisy training records"):
        FDIModule(FDIMLP(6, 5, noise_input=True))


def test_noise_aware_network_trained_on_noisy_records_keeps_its_clean_accuracy(tmp_path):
    """Trained end to end on records with up to 10 % noise, a network told each record's level resolves
    clean records better than the same network trained the same way without it (it learns when the fine
    detail of the coefficients can be trusted), and is no worse on noisy ones."""
    from surrogate_data import faults, signals

    k, kv = faults(600, 0).float(), faults(200, 1).float()
    y, yv = signals(k), signals(kv)
    pod = POD(10).fit(y)
    gappy = GappyPOD(pod.modes_, pod.mean_, build_selector("greedy", n_points=20).fit(pod.modes_).indices_)
    s, sv = gappy.select(y), gappy.select(yv)
    scale, scale_v = rms(y), rms(yv)
    noisy_v = add_noise(sv, scale_v, 0.1, torch.Generator().manual_seed(5))
    err = {}
    for aware in (False, True):
        torch.manual_seed(0)
        levels = torch.rand(len(s)) * 0.1
        net = FDIMLP(10, 24, n_layers=2, input_scaling="robust", noise_input=aware, max_noise=0.1)
        net.set_normalization(gappy(s)[0], levels if aware else None)
        module = FDIModule(net, lr=1e-2, gappy=gappy, augment=SignalAugment(noise=0.1, max_missing=0))
        _, keep = _fit(module, TensorDataset(s, k, scale), TensorDataset(sv, kv, scale_v), 100, 32, tmp_path)
        keep.restore(module)
        with torch.no_grad():
            err[aware] = (
                err_k(net(gappy(sv)[0], torch.zeros(len(sv))), kv),
                err_k(net(gappy(noisy_v)[0], torch.full((len(sv),), 0.1)), kv),
            )
    assert err[True][0] < 0.9 * err[False][0]
    assert err[True][1] < 1.02 * err[False][1]


def test_noise_level_is_unbiased_for_white_noise_and_ignores_sparse_spikes():
    from phm_torch.surrogates.augment import clipped_mean_factor, noise_level

    g = torch.Generator().manual_seed(0)
    white = torch.randn(64, 10001, generator=g, dtype=torch.float64)
    assert float(noise_level(white).mean()) == pytest.approx(1.0, abs=0.003)  # the clipped-mean factor
    assert clipped_mean_factor() == pytest.approx(1.9401301101495292, rel=1e-12)  # the literal in the code
    windowed = noise_level(white, 2048)
    assert float(windowed.mean()) == pytest.approx(1.0, abs=0.01) and float(windowed.std()) < 0.05
    # a smooth record with rare spikes (ringing after commutation edges) and 1 % noise still reads ~1 %
    t = torch.linspace(0, 0.5, 10001, dtype=torch.float64)
    record = 2.0 + torch.sin(2 * math.pi * 7 * t)
    spiky = record.clone()
    spiky[::500] += 0.5
    rel = noise_level(
        torch.stack([record, spiky])
        + 0.01 * rms(record.unsqueeze(0)) * torch.randn(2, 10001, generator=g, dtype=torch.float64)
    )
    torch.testing.assert_close(rel, torch.full((2,), 0.01, dtype=torch.float64), rtol=0.05, atol=0.0)
    assert float(noise_level(spiky.unsqueeze(0))) < 1e-3
    torch.testing.assert_close(torch.jit.script(noise_level)(white[:4], 2048), windowed[:4])
