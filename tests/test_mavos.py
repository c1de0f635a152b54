"""MaVOS maths on hand-made co-visibility graphs with known answers."""
import math

import numpy as np
import pytest

from manifoldneus.scheduling.mavos import (
    bottleneck_weight,
    connected_components,
    is_connected_subset,
    mavos_schedule,
    n_anchors_for,
    normalise,
    spectral_embedding,
)

ALPHA = 0.65  # schedule.alpha's default (its one home is the `schedule` section)


def path_graph(n, w=1.0):
    W = np.zeros((n, n))
    for i in range(n - 1):
        W[i, i + 1] = W[i + 1, i] = w
    return W


def ring_graph(n, w=1.0):
    W = path_graph(n, w)
    W[0, n - 1] = W[n - 1, 0] = w
    return W


def star_plus():
    """Hub 0 strongly connected to 1..4; a chain of weak views 5-7 hanging off view 4."""
    W = np.zeros((8, 8))
    W[0, 1:5] = [50, 40, 30, 20]
    W[1:5, 0] = W[0, 1:5]
    W[4, 5] = W[5, 4] = 2
    W[5, 6] = W[6, 5] = 2
    W[6, 7] = W[7, 6] = 2
    return W


# --------------------------------------------------------------------------- spectral


def test_path_graph_fiedler_is_monotone():
    W = path_graph(10)
    emb = spectral_embedding(W, d=3)
    f = emb.phi[:, 0]
    d = np.diff(f)
    assert np.all(d > 0) or np.all(d < 0)
    assert emb.d == 3 and emb.phi.shape == (10, 3)
    assert np.all(np.diff(emb.eigenvalues) >= -1e-12)
    assert abs(emb.trivial_eigenvalue) < 1e-9
    # sign convention: the entry of largest magnitude of each coordinate is positive
    for k in range(3):
        col = emb.phi[:, k] * np.sqrt(W.sum(1))
        assert col[np.argmax(np.abs(col))] > 0


def test_ring_graph_embeds_as_circle_in_order():
    n = 12
    emb = spectral_embedding(ring_graph(n), d=2)
    xy = emb.phi[:, :2]
    r = np.linalg.norm(xy, axis=1)
    assert np.allclose(r, r.mean(), rtol=1e-6)
    ang = np.unwrap(np.arctan2(xy[:, 1], xy[:, 0]))
    step = np.diff(ang)
    assert np.allclose(np.abs(step), 2 * np.pi / n, atol=1e-6)
    assert np.all(np.sign(step) == np.sign(step[0]))


def test_spectral_d_capped_and_disconnected():
    W = np.zeros((6, 6))
    W[:4, :4] = ring_graph(4)
    W[4, 5] = W[5, 4] = 3
    emb = spectral_embedding(W, d=8)
    assert emb.d == 3 and emb.d_requested == 8
    assert emb.in_component.tolist() == [True] * 4 + [False] * 2
    assert np.all(np.isfinite(emb.phi)) and np.all(emb.phi[4:] == 0)


def test_dense_and_sparse_solvers_agree():
    rng = np.random.default_rng(0)
    n = 40
    W = ring_graph(n) * 5
    extra = rng.integers(0, n, (30, 2))
    for i, j in extra:
        if i != j:
            W[i, j] = W[j, i] = rng.integers(1, 4)
    a = spectral_embedding(W, d=3, dense_max=1000)
    b = spectral_embedding(W, d=3, dense_max=10)
    assert a.solver == "dense" and b.solver == "sparse"
    assert np.allclose(a.eigenvalues, b.eigenvalues, atol=1e-8)
    # compare only non-degenerate coordinates: distances are the robust invariant
    da = np.linalg.norm(a.phi[:, None] - a.phi[None], axis=-1)
    db = np.linalg.norm(b.phi[:, None] - b.phi[None], axis=-1)
    gaps = np.diff(spectral_embedding(W, d=4).eigenvalues)
    assert gaps.min() > 1e-6  # simple eigenvalues: vectors unique up to sign, fixed by the convention
    assert np.allclose(a.phi, b.phi, atol=1e-6)
    assert np.allclose(da, db, atol=1e-6)


def test_components_and_connectivity():
    W = np.zeros((5, 5))
    W[0, 1] = W[1, 0] = 1
    W[2, 3] = W[3, 2] = W[3, 4] = W[4, 3] = 1
    assert connected_components(W) == [[2, 3, 4], [0, 1]]
    assert is_connected_subset(W, [2, 3, 4])
    assert not is_connected_subset(W, [2, 4])
    assert not is_connected_subset(W, [0, 2])
    V = path_graph(4, 10.0)
    V[1, 2] = V[2, 1] = 3.0
    V[0, 3] = V[3, 0] = 1.0
    assert bottleneck_weight(V, [0, 1, 2, 3]) == 3.0  # the weak middle link of the max spanning tree
    assert bottleneck_weight(V, [0, 3]) == 1.0
    assert bottleneck_weight(W, [0, 2]) == 0.0


# --------------------------------------------------------------------------- helpers


def test_normalise_ties_no_nan():
    assert normalise(np.array([3.0, 3.0])).tolist() == [0.0, 0.0]
    assert normalise(np.array([3.0])).tolist() == [0.0]
    assert normalise(np.array([0.0, 0.0])).tolist() == [0.0, 0.0]
    assert normalise(np.array([1.0, 3.0, 2.0])).tolist() == [0.0, 1.0, 0.5]
    assert normalise(np.array([3.0, 3.0]), tie=1.0).tolist() == [1.0, 1.0]  # S~: all equally optimisable
    assert normalise(np.array([2.0, 5.0, 0.0]), lo_hi=(1.0, 3.0)).tolist() == [0.5, 1.0, 0.0]  # a given range, clipped
    assert normalise(np.array([2.0]), lo_hi=(1.0, 1.0)).tolist() == [0.0]


def test_n_anchors():
    assert n_anchors_for(49, 30) == 15  # ceil(14.7)
    assert n_anchors_for(10, 30) == 3  # exactly 3, no float ceil to 4
    assert n_anchors_for(10, 100) == 10
    assert n_anchors_for(10, 1) == 1


# --------------------------------------------------------------------------- scheduling


def test_first_anchor_is_argmax_c_and_alpha1_picks_strongest():
    W = star_plus()
    s = mavos_schedule(W, None, alpha=1.0,
                       anchor_percent=50, successors_per_round=2, coverage="E")
    assert s.picks[0] == 0  # largest c
    # alpha = 1: next picks follow the strongest connection to O: 1 (50), 2 (40), 3 (30)
    assert s.picks[1:4] == [1, 2, 3]
    assert s.S[0] == 1.0 and s.L[0] == 1.0


def test_alpha0_picks_spectrally_farthest():
    W = path_graph(9, 5.0)
    W[4, 3] = W[3, 4] = W[4, 5] = W[5, 4] = 20.0  # view 4 has the largest c
    emb = spectral_embedding(W, d=3)
    s = mavos_schedule(W, emb.phi, alpha=0.0, anchor_percent=100 * 3 / 9, successors_per_round=3)
    assert s.picks[0] == 4
    d = np.linalg.norm(emb.phi - emb.phi[4], axis=1)
    assert s.picks[1] == int(np.argmax(d))
    assert set(s.picks[1:3]) == {0, 8}  # the two ends of the path
    # alpha = 1 instead grows a connected cluster around view 4
    s1 = mavos_schedule(W, emb.phi, alpha=1.0, anchor_percent=100 * 3 / 9, successors_per_round=3)
    assert set(s1.anchors) == {3, 4, 5}
    assert is_connected_subset(W, s1.anchors)
    assert not is_connected_subset(W, s.anchors)


def test_fps_equals_alpha0_order_and_scores_are_coverage():
    W = ring_graph(10, 3.0)
    W[0, 5] = W[5, 0] = 1.0
    W[2, 3] = W[3, 2] = 9.0
    emb = spectral_embedding(W, d=4)
    f = mavos_schedule(W, emb.phi, strategy="fps", anchor_percent=40, successors_per_round=3)
    a0 = mavos_schedule(W, emb.phi, alpha=0.0, anchor_percent=40, successors_per_round=3)
    assert f.picks == a0.picks
    assert f.picks[0] == int(np.argmax(W.sum(1)))
    assert np.allclose(f.S, f.C)
    assert f.settings["alpha"] is None


def test_rounds_and_last_round_takes_rest():
    rng = np.random.default_rng(1)
    n = 49
    W = ring_graph(n, 10)
    for _ in range(60):
        i, j = rng.integers(0, n, 2)
        if i != j:
            W[i, j] = W[j, i] = rng.integers(1, 30)
    emb = spectral_embedding(W, d=8)
    s = mavos_schedule(W, emb.phi, alpha=ALPHA)
    assert s.settings["round_sizes"] == [15, 20, 14]
    assert s.n_rounds == 3 and s.n_anchors == 15
    assert sorted(s.picks) == list(range(n))
    assert sorted(s.order.tolist()) == list(range(n))
    assert [s.role[i] for i in s.picks[:15]] == ["anchor"] * 15
    assert s.role[s.picks[15]] == "round1" and s.role[s.picks[-1]] == "round2"
    assert np.all(s.round[s.picks] == np.repeat([0, 1, 2], [15, 20, 14]))
    for a in (s.S, s.L, s.C, s.s_tilde, s.s_tilde_rounds):
        assert np.all(np.isfinite(a))
        assert a.min() >= 0 and a.max() <= 1 + 1e-12
    # S~ per round: over all views scheduled up to that round, min-max normalised
    for r in range(3):
        views = np.flatnonzero(s.optimised[r])
        assert len(views) == [15, 35, 49][r]
        vals = s.s_tilde_rounds[r, views]
        assert vals.max() == pytest.approx(1.0) and vals.min() == pytest.approx(0.0)
        assert np.all(s.s_tilde_rounds[r, ~s.optimised[r]] == 0)
    for v in range(n):
        assert s.s_tilde[v] == s.s_tilde_rounds[s.round[v], v]
    # S is alpha L + (1 - alpha) C at pick time
    assert np.allclose(s.S, 0.65 * s.L + 0.35 * s.C)


def test_uniform_one_round():
    W = ring_graph(7, 2.0)
    W[1, 2] = W[2, 1] = 5
    s = mavos_schedule(W, spectral_embedding(W).phi, strategy="uniform")
    assert s.n_rounds == 1 and s.n_anchors == 7
    assert set(s.role) == {"anchor"}
    assert np.all(s.s_tilde == 1.0)
    assert sorted(s.picks) == list(range(7))
    # it uses neither alpha nor K nor M, so nothing it returns depends on them
    t = mavos_schedule(W, spectral_embedding(W).phi, strategy="uniform", alpha=0.1, anchor_percent=80,
                       successors_per_round=2)
    assert t.settings == s.settings and t.picks == s.picks
    for a, b in ((s.S, t.S), (s.order, t.order), (s.s_tilde_rounds, t.s_tilde_rounds), (s.L, t.L)):
        assert np.array_equal(a, b)


def test_ties_are_deterministic_and_nan_free():
    W = np.ones((6, 6)) - np.eye(6)  # complete graph: everything ties
    s = mavos_schedule(W, None, coverage="E", anchor_percent=50, successors_per_round=1, alpha=ALPHA)
    assert s.picks[0] == 0
    assert s.picks == sorted(s.picks)  # lowest index wins every tie (all row distances equal on K_n)
    for a in (s.S, s.L, s.C, s.s_tilde, s.s_tilde_rounds):
        assert np.all(np.isfinite(a))
    assert s.settings["round_sizes"] == [3, 1, 1, 1]
    assert np.all(s.L[s.picks[1:]] == 0.0) and np.all(s.C[s.picks[1:]] == 0.0)  # ties -> 0
    assert s.S[0] == 1.0 and np.all(s.S[s.picks[1:]] == 0.0)
    assert np.all(s.s_tilde_rounds[1:][s.optimised[1:]] >= 0)
    assert s.s_tilde[s.picks[-1]] == 0.0  # the single last candidate is not "most optimisable"
    # spectral coverage on a fully degenerate spectrum: still deterministic and finite
    emb = spectral_embedding(W, d=3)
    a = mavos_schedule(W, emb.phi, anchor_percent=50, successors_per_round=1, alpha=ALPHA)
    b = mavos_schedule(W, emb.phi, anchor_percent=50, successors_per_round=1, alpha=ALPHA)
    assert a.picks == b.picks and np.all(np.isfinite(a.S))


def test_disconnected_graph_excludes_small_component():
    W = np.zeros((7, 7))
    W[:5, :5] = ring_graph(5, 4)
    W[5, 6] = W[6, 5] = 100  # a strong pair, but the smaller component
    emb = spectral_embedding(W, d=8)
    s = mavos_schedule(W, emb.phi, c=W.sum(1), alpha=ALPHA)
    assert s.role[5] == s.role[6] == "excluded"
    assert s.round[5] == -1 and s.order[6] == -1 and s.s_tilde[5] == 0
    assert sorted(s.picks) == [0, 1, 2, 3, 4]
    assert s.n_anchors == math.ceil(0.3 * 5)
    assert s.schedulable.tolist() == [True] * 5 + [False] * 2


def test_single_view_component():
    W = np.zeros((3, 3))
    emb = spectral_embedding(W, d=4)
    assert emb.d == 0
    s = mavos_schedule(W, emb.phi, alpha=ALPHA)
    assert s.picks == [0] and s.role[1] == "excluded"
    assert np.all(np.isfinite(s.S))


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"anchor_percent": 0}, "anchor_percent"),
        ({"anchor_percent": 101}, "anchor_percent"),
        ({"anchor_percent": -5}, "anchor_percent"),
        ({"successors_per_round": 0}, "successors_per_round"),
        ({"successors_per_round": 2.5}, "successors_per_round"),
        ({"alpha": 1.2}, "alpha"),
        ({"alpha": -0.1}, "alpha"),
        ({"alpha": float("nan")}, "alpha"),
        ({"strategy": "random"}, "strategy"),
        ({"coverage": "XE"}, "coverage"),
        ({"alpha": None}, "the mavos strategy needs alpha"),
    ],
)
def test_guard_rails(kwargs, name):
    W = ring_graph(6)
    with pytest.raises(ValueError, match=name):
        mavos_schedule(W, spectral_embedding(W).phi, **{"alpha": ALPHA, **kwargs})


def test_bad_graphs_rejected():
    with pytest.raises(ValueError, match="symmetric"):
        mavos_schedule(np.triu(ring_graph(5)), coverage="E", alpha=ALPHA)
    with pytest.raises(ValueError, match="phi"):
        mavos_schedule(ring_graph(5), None, coverage="SE", alpha=ALPHA)
    with pytest.raises(ValueError, match="d"):
        spectral_embedding(ring_graph(5), d=0)


def test_forced_last_pick_uses_previous_candidate_range():
    W = np.zeros((4, 4))
    W[0, 1] = W[1, 0] = 10
    W[1, 2] = W[2, 1] = 10
    W[0, 3] = W[3, 0] = 1
    W[2, 3] = W[3, 2] = 5
    s = mavos_schedule(W, None, coverage="E", alpha=1.0, anchor_percent=25, successors_per_round=3)
    assert s.picks[0] == 1  # largest c (20)
    assert s.picks[1] == 0  # tie 0 / 2 on L (10 each): lowest index
    assert s.picks[2] == 2  # L_raw 10 vs view 3's 1
    # view 3 is forced last: L_raw = 1 + 5 = 6 rescaled with the previous range (1, 10)
    assert s.L_raw[3] == 6 and s.S[3] == pytest.approx(5 / 9)


def test_s_tilde_from_rank():
    W = ring_graph(10, 3.0)
    W[2, 3] = W[3, 2] = 9.0
    emb = spectral_embedding(W, d=4)
    a = mavos_schedule(W, emb.phi, anchor_percent=40, successors_per_round=4, alpha=ALPHA)
    b = mavos_schedule(W, emb.phi, anchor_percent=40, successors_per_round=4, s_tilde_from="rank", alpha=ALPHA)
    assert a.picks == b.picks and np.allclose(a.S, b.S)
    for r, n in enumerate([4, 8, 10]):
        views = np.flatnonzero(b.optimised[r])
        assert len(views) == n
        got = b.s_tilde_rounds[r, b.picks[:n]]
        assert np.allclose(got, 1 - np.arange(n) / (n - 1))
    assert b.settings["s_tilde_from"] == "rank"
    with pytest.raises(ValueError, match="s_tilde_from"):
        mavos_schedule(W, emb.phi, s_tilde_from="order", alpha=ALPHA)
