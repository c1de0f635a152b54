"""The MaVOS-gated coarse-to-fine gate: band weights for known S~, k and t."""
import math

import torch

from manifoldneus.neural.gate import GateParams, band_weights, barf_weights, base_progress

L = 6
T = 1000


def w(a):
    return (1 - math.cos(math.pi * min(max(a, 0.0), 1.0))) / 2


def test_lambda_zero_is_barf():
    p = GateParams(lam=0.0)
    view = torch.tensor([0, 1, 2])
    s = torch.tensor([0.0, 0.5, 1.0])
    for step in (0, 100, 250, 300, 499):
        got = band_weights(view, step, T, s, L, p)
        a = base_progress(step, T, p, L)
        expect = barf_weights(a, L).expand(3, L)
        torch.testing.assert_close(got, expect)
    assert band_weights(view, 600, T, s, L, p) is None  # all bands on after the window


def test_known_values_full_gate():
    p = GateParams(lam=0.3, start=0.1, end=0.5)
    step = 300  # t/T = 0.3 -> a = (0.3 - 0.1) / 0.4 * 6 = 3
    view = torch.tensor([0, 1])
    s = torch.tensor([1.0, 0.0])
    got = band_weights(view, step, T, s, L, p)
    for k in range(L):
        shift = 0.3 * 1.0 * (k + 1) / L * 0.3 * L
        assert abs(got[0, k].item() - w(3 + shift - k)) < 1e-6
        assert abs(got[1, k].item() - w(3 - k)) < 1e-6  # S~ = 0: no shift
    # easy views unlock fine bands earlier, and never less than a hard view
    assert (got[0] >= got[1]).all() and got[0, 3] > got[1, 3]


def test_ablation_switches():
    view = torch.tensor([0])
    s = torch.tensor([0.5])
    step = 200  # t/T = 0.2, a = 1.5
    only_s = band_weights(view, step, T, s, L, GateParams(use_eta_f=False, use_eta_t=False))
    for k in range(L):
        assert abs(only_s[0, k].item() - w(1.5 + 0.3 * 0.5 * L - k)) < 1e-6
    with_f = band_weights(view, step, T, s, L, GateParams(use_eta_t=False))
    for k in range(L):
        assert abs(with_f[0, k].item() - w(1.5 + 0.3 * 0.5 * (k + 1) - k)) < 1e-6
    no_s = band_weights(view, step, T, s, L, GateParams(use_s=False, use_eta_f=False, use_eta_t=False))
    for k in range(L):
        assert abs(no_s[0, k].item() - w(1.5 + 0.3 * L - k)) < 1e-6
    assert band_weights(view, step, T, s, L, GateParams(enabled=False)) is None


def test_vectorised_over_rays():
    view = torch.randint(0, 10, (4096,))
    s = torch.rand(10)
    out = band_weights(view, 333, T, s, L, GateParams())
    assert out.shape == (4096, L) and torch.isfinite(out).all() and (out >= 0).all() and (out <= 1).all()
    # rays of one view share weights
    i = view[0]
    assert torch.allclose(out[view == i], out[view == i][0].expand_as(out[view == i]))


def test_views_an_earlier_round_fitted_keep_their_coarse_bands():
    """successors.regate_kept: the views an earlier round optimised start the gate's progress at
    kept x L bands (1: every band from the round's first step); the round's new views start at 0."""
    view = torch.arange(10).repeat(50)
    s = torch.rand(10)
    kept = (torch.arange(10) < 7).float()  # views 0..6 were fitted before; 7, 8, 9 are new
    new = ~kept.bool()[view]
    for step in (0, 100, 333):
        plain = band_weights(view, step, T, s, L, GateParams())
        every = band_weights(view, step, T, s, L, GateParams(), kept * L)
        half = band_weights(view, step, T, s, L, GateParams(), kept * L / 2)
        assert torch.equal(every[new], plain[new]) and torch.equal(half[new], plain[new])
        assert torch.equal(every[~new], torch.ones_like(every[~new]))
        # the coarse half is on from the start, the finer bands no lower than the plain gate's
        assert torch.equal(half[~new][:, : L // 2], torch.ones_like(half[~new][:, : L // 2]))
        assert (half[~new] >= plain[~new]).all()
    assert (band_weights(view, 0, T, s, L, GateParams(), kept * L / 2)[~new][:, -1] < 1).all()
