"""Spectral view embedding and MaVOS view scheduling (METHOD.md stages 5 and 6). Pure numpy/scipy.

Definitions, including the choices the paper leaves open (each one named here and nowhere else):

* Co-visibility graph: ``W[i, j] = n_ij >= 0`` (symmetric; the diagonal is ignored), cumulative
  count ``c_i = sum_j n_ij``. Only views in the largest connected component are embedded and
  scheduled; the others are flagged (``in_component`` False, schedule role ``"excluded"``).
  The largest component is the one with most views, ties broken by its lowest view index.
* Spectral embedding: normalised Laplacian ``L = I - D^-1/2 W D^-1/2`` of the largest component,
  the eigenvectors ``u_1..u_d`` of its ``d`` smallest non-trivial eigenvalues (``u_0`` ~ D^1/2 1 is
  skipped), ``phi_i = D_ii^-1/2 [u_1(i), ..., u_d(i)]``. ``d`` is capped at ``n_comp - 1``.
  Each eigenvector's sign is fixed so that its entry of largest magnitude is positive (ties: lowest
  index). Within a repeated eigenvalue the basis is arbitrary (``d_SE`` is only basis-free when
  whole eigenspaces are kept). Dense ``scipy.linalg.eigh`` up to ``DENSE_MAX`` views, else
  ``scipy.sparse.linalg.eigsh`` on the largest eigenvalues of ``D^-1/2 W D^-1/2`` (same vectors).
* Coverage distances: ``"SE"``: ``d(i, j) = |phi_i - phi_j|``; ``"E"``: Euclidean distance of the
  raw rows of W, ``|W_i - W_j|``.
* Normalisation over the candidates: ``(x - min) / (max - min)``; when all candidates tie
  (``max == min``) every candidate gets 0 (never NaN): a term that cannot rank the candidates
  credits none of them. The very last pick (a single candidate left: a forced pick) is instead
  normalised with the (min, max) of the previous pick's candidate set, clipped to [0, 1], so that its
  S is comparable with the other picks (a tie rule would give it S = 0 or 1, an outlier that
  dominates the min-max normalisation of S~ in the last round).
* Greedy picking (strategy ``"mavos"``): with ``O`` the views scheduled so far and each candidate i,
  ``L_i = sum_{j in O} n_ij`` and ``C_i = min_{j in O} d(i, j)``, each normalised over the
  candidates, ``S_i = alpha L_i + (1 - alpha) C_i``; the argmax (ties: lowest index) is added to
  ``O`` and everything is re-scored. With ``O`` empty (the very first pick) the seed is
  ``argmax c_i`` (ties: lowest index), recorded with ``S = L = C = 1`` (``L_raw = c_i``, ``C_raw = 0``
  standing for the infinite distance to an empty set).
  Anchors: ``ceil(K/100 * n)`` picks (n = number of schedulable views, i.e. of the largest
  component; at least 1, at most n). Successor rounds r = 1, 2, ...: ``M`` picks each, the last round
  takes the rest (it may hold fewer than M views).
* ``"fps"``: farthest-point sampling with the same distance and the same first view, anchors and
  rounds: the pick is ``argmax C_i`` and the recorded score is ``S_i = C_i`` (alpha is ignored; the
  pick order equals that of ``"mavos"`` with alpha = 0). ``L_i`` is still recorded.
* ``"uniform"``: every schedulable view in one round (round 0, role ``"anchor"``): the NeuS-BARF
  baseline. Views are still ranked by the MaVOS greedy scores (recorded for plots), but
  ``S~ = 1`` for every view (no per-view optimisability; use lambda = 0 for plain BARF).
* Optimisability ``S~``: the views optimised in round r are all views scheduled in rounds 0..r
  (successor rounds optimise every scheduled view jointly). ``S~[r, i]`` is ``S_i`` (at pick
  time) min-max normalised over that set, ties -> 1 (all equally optimisable); entries of views not
  optimised in round r are 0 and ``optimised[r, i]`` is False. The per-view value ``s_tilde[i]`` is
  the one of its own round, ``S~[round_i, i]``. Excluded views have ``s_tilde = 0``.
  Variant ``s_tilde_from="rank"`` (not in METHOD.md; default ``"score"`` is): S~ from the pick
  order instead of the score, ``1 - rank / (n_r - 1)`` over the same set (first pick 1, last 0).
  Why: on real graphs the greedy S at pick time clusters (e.g. scan24: 0.65..0.70, the L-best
  candidate usually wins with C ~ 0) while the seed has S = 1, so the score-based S~ of every view
  but the seed lies in ~[0, 0.15]; the rank variant spreads the same ordering over [0, 1].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

DENSE_MAX = 500
STRATEGIES = ("mavos", "fps", "uniform")
S_TILDE_FROM = ("score", "rank")
COVERAGES = ("SE", "E")


# --------------------------------------------------------------------------- graph helpers


def check_graph(W: np.ndarray) -> np.ndarray:
    """Validate a co-visibility matrix; returns a float64 copy with zero diagonal."""
    W = np.array(W, dtype=np.float64)
    if W.ndim != 2 or W.shape[0] != W.shape[1]:
        raise ValueError(f"W: expected a square [N,N] matrix, got shape {W.shape}")
    if not np.all(np.isfinite(W)):
        raise ValueError("W: contains NaN or infinite entries")
    np.fill_diagonal(W, 0.0)
    if np.any(W < 0):
        raise ValueError("W: negative co-visibility weights")
    scale = max(1.0, float(np.abs(W).max(initial=0.0)))
    if not np.allclose(W, W.T, atol=1e-9 * scale):
        raise ValueError("W: not symmetric")
    return 0.5 * (W + W.T)


def covisibility_matrix(n_views: int, pairs, counts, min_inliers: int = 0) -> np.ndarray:
    """W [N,N] float64 from pairs [P,2] and their inlier counts [P]: symmetric, zero diagonal; pairs
    with fewer than ``min_inliers`` (at least 1) get no edge; a pair listed twice keeps the larger count."""
    W = np.zeros((n_views, n_views))
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    counts = np.asarray(counts, np.float64).reshape(-1)
    keep = (counts >= max(min_inliers, 1)) & (pairs[:, 0] != pairs[:, 1])
    i, j, c = pairs[keep, 0], pairs[keep, 1], counts[keep]
    np.maximum.at(W, (i, j), c)
    np.maximum.at(W, (j, i), c)
    return W


def connected_components(W: np.ndarray) -> list[list[int]]:
    """Connected components of the graph with edges W > 0, largest first (ties: lowest index)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components as cc

    W = check_graph(W)
    n, labels = cc(csr_matrix(W > 0), directed=False)
    comps = [sorted(np.flatnonzero(labels == k).tolist()) for k in range(n)]
    comps.sort(key=lambda c: (-len(c), c[0]))
    return comps


def component_labels(W: np.ndarray) -> np.ndarray:
    """[N] int32: each view's index in :func:`connected_components` (0 = the largest)."""
    labels = np.zeros(len(W), np.int32)
    for k, comp in enumerate(connected_components(W)):
        labels[comp] = k
    return labels


def largest_component(W: np.ndarray) -> np.ndarray:
    """Indices (sorted) of the largest connected component."""
    return np.asarray(connected_components(W)[0], dtype=np.int64)


def is_connected_subset(W: np.ndarray, subset) -> bool:
    """Whether the subgraph of W (edges W > 0) induced by ``subset`` is connected."""
    subset = np.asarray(sorted(set(int(i) for i in subset)), dtype=np.int64)
    if len(subset) <= 1:
        return len(subset) == 1
    sub = np.asarray(W, dtype=np.float64)[np.ix_(subset, subset)]
    return len(connected_components(sub)) == 1


def bottleneck_weight(W: np.ndarray, subset) -> float:
    """Largest t such that the subgraph induced by ``subset`` with edges ``W >= t`` is connected
    (the weakest link of its maximum spanning tree); 0 if it is not connected at all, inf for one view."""
    subset = np.asarray(sorted(set(int(i) for i in subset)), dtype=np.int64)
    if len(subset) <= 1:
        return float("inf") if len(subset) == 1 else 0.0
    sub = np.asarray(W, dtype=np.float64)[np.ix_(subset, subset)]
    if not is_connected_subset(sub, range(len(subset))):
        return 0.0
    weights = np.unique(sub[sub > 0])
    lo, hi = 0, len(weights) - 1  # weights[lo] always connects; find the largest that does
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if is_connected_subset(np.where(sub >= weights[mid], sub, 0.0), range(len(subset))):
            lo = mid
        else:
            hi = mid - 1
    return float(weights[lo])


# --------------------------------------------------------------------------- spectral embedding


@dataclass
class SpectralEmbedding:
    phi: np.ndarray  # [N, d] float64; rows of views outside the component are 0
    eigenvalues: np.ndarray  # [d] the non-trivial eigenvalues used (ascending)
    trivial_eigenvalue: float  # the skipped smallest eigenvalue (~0)
    in_component: np.ndarray  # [N] bool
    component: np.ndarray  # indices of the embedded component
    d_requested: int
    d: int  # used (capped)
    solver: str  # "dense" | "sparse"


def _fix_signs(U: np.ndarray) -> np.ndarray:
    U = U.copy()
    for k in range(U.shape[1]):
        i = int(np.argmax(np.abs(U[:, k])))  # first maximum: lowest index
        if U[i, k] < 0:
            U[:, k] = -U[:, k]
    return U


def spectral_embedding(W: np.ndarray, d: int = 8, component=None, dense_max: int = DENSE_MAX) -> SpectralEmbedding:
    """Spectral coordinates of the views of ``component`` (default: the largest component)."""
    if int(d) != d or d < 1:
        raise ValueError(f"d: expected an integer >= 1, got {d!r}")
    d = int(d)
    W = check_graph(W)
    N = W.shape[0]
    comp = largest_component(W) if component is None else np.asarray(sorted(component), dtype=np.int64)
    n = len(comp)
    Wc = W[np.ix_(comp, comp)]
    deg = Wc.sum(1)
    if n > 1 and np.any(deg <= 0):
        raise ValueError("spectral_embedding: the component has an isolated view (zero degree)")
    d_used = max(0, min(d, n - 1))
    in_comp = np.zeros(N, dtype=bool)
    in_comp[comp] = True
    phi = np.zeros((N, d_used))
    if n <= 1 or d_used == 0:
        return SpectralEmbedding(phi, np.zeros(0), 0.0, in_comp, comp, d, d_used, "dense")
    inv_sqrt = 1.0 / np.sqrt(deg)
    A = Wc * inv_sqrt[:, None] * inv_sqrt[None, :]  # D^-1/2 W D^-1/2
    A = 0.5 * (A + A.T)
    if n <= dense_max or d_used + 1 >= n - 1:
        import scipy.linalg

        L = np.eye(n) - A
        evals, evecs = scipy.linalg.eigh(L)
        solver = "dense"
    else:
        import scipy.sparse
        import scipy.sparse.linalg

        mu, vecs = scipy.sparse.linalg.eigsh(
            scipy.sparse.csr_matrix(A), k=d_used + 1, which="LA", v0=np.sqrt(deg) / np.linalg.norm(np.sqrt(deg))
        )
        evals = 1.0 - mu
        order = np.argsort(evals, kind="stable")
        evals, evecs = evals[order], vecs[:, order]
        solver = "sparse"
    evals = np.clip(evals, 0.0, 2.0)
    U = _fix_signs(evecs[:, 1 : d_used + 1])
    phi[comp] = U * inv_sqrt[:, None]
    return SpectralEmbedding(phi, evals[1 : d_used + 1].copy(), float(evals[0]), in_comp, comp, d, d_used, solver)


# --------------------------------------------------------------------------- distances


def coverage_distances(W: np.ndarray, phi: np.ndarray | None, coverage: str = "SE") -> np.ndarray:
    """Pairwise [N,N] distances: ``"SE"`` on spectral coordinates, ``"E"`` on rows of W."""
    if coverage not in COVERAGES:
        raise ValueError(f"coverage: {coverage!r} is not one of {COVERAGES}")
    if coverage == "SE":
        if phi is None:
            raise ValueError("coverage 'SE' needs the spectral coordinates phi")
        X = np.asarray(phi, dtype=np.float64)
    else:
        X = check_graph(W)
    X = X.reshape(X.shape[0], -1)
    diff = X[:, None, :] - X[None, :, :]
    return np.sqrt((diff**2).sum(-1))


def normalise(x: np.ndarray, lo_hi=None, tie: float = 0.0) -> np.ndarray:
    """Min-max normalise to [0, 1]: ``(x - lo) / (hi - lo)`` over x's own (min, max), or over a
    given ``lo_hi`` (clipped to [0, 1]); an empty range (all candidates tie) gives ``tie`` to all."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return x.copy()
    lo, hi = (float(x.min()), float(x.max())) if lo_hi is None else (float(lo_hi[0]), float(lo_hi[1]))
    if not hi > lo:
        return np.full_like(x, tie)
    return np.clip((x - lo) / (hi - lo), 0.0, 1.0)


# --------------------------------------------------------------------------- scheduling


@dataclass
class Schedule:
    """Per-view results (arrays of length N, view order); see the module docstring."""

    role: list  # "anchor" | "round1" | "round2" ... | "excluded"
    round: np.ndarray  # int [N]: 0 = anchor, r >= 1 successor round, -1 excluded
    order: np.ndarray  # int [N]: global pick order (0 = first anchor), -1 excluded
    S: np.ndarray  # float [N] score at pick time
    L: np.ndarray  # float [N] normalised local constraint at pick time
    C: np.ndarray  # float [N] normalised coverage at pick time
    L_raw: np.ndarray  # sum_{j in O} n_ij at pick time
    C_raw: np.ndarray  # min_{j in O} d(i, j) at pick time (inf for the first view -> stored as 0)
    s_tilde: np.ndarray  # float [N] optimisability in its own round
    s_tilde_rounds: np.ndarray  # float [R, N]
    optimised: np.ndarray  # bool [R, N]: view optimised in round r (scheduled in rounds <= r)
    picks: list  # view indices in pick order
    n_rounds: int  # R, including the anchor round
    n_anchors: int
    schedulable: np.ndarray  # bool [N]
    settings: dict = field(default_factory=dict)

    @property
    def anchors(self) -> list:
        return [int(i) for i in self.picks[: self.n_anchors]]

    def round_views(self, r: int) -> list:
        """Views added in round r, in pick order."""
        return [int(i) for i in self.picks if self.round[i] == r]


def _validate(strategy, alpha, anchor_percent, successors_per_round, coverage):
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy: {strategy!r} is not one of {STRATEGIES}")
    if coverage not in COVERAGES:
        raise ValueError(f"coverage: {coverage!r} is not one of {COVERAGES}")
    if alpha is None and strategy == "mavos":  # its value lives in the `schedule` section, not here
        raise ValueError("alpha: the mavos strategy needs alpha (S = alpha L + (1 - alpha) C)")
    if alpha is not None:
        try:
            alpha = float(alpha)
        except (TypeError, ValueError):
            raise ValueError(f"alpha: expected a number in [0, 1], got {alpha!r}") from None
        if not (0.0 <= alpha <= 1.0):
            raise ValueError(f"alpha: {alpha} is outside [0, 1]")
    try:
        K = float(anchor_percent)
    except (TypeError, ValueError):
        raise ValueError(f"anchor_percent: expected a number in (0, 100], got {anchor_percent!r}") from None
    if not (0.0 < K <= 100.0):
        raise ValueError(f"anchor_percent: {anchor_percent} is outside (0, 100]")
    if isinstance(successors_per_round, bool) or int(successors_per_round) != successors_per_round:
        raise ValueError(f"successors_per_round: expected an integer >= 1, got {successors_per_round!r}")
    M = int(successors_per_round)
    if M < 1:
        raise ValueError(f"successors_per_round: {M} is below 1")
    return alpha, K, M


def n_anchors_for(n: int, anchor_percent: float) -> int:
    """ceil(K% of n), within [1, n] (rounded first to absorb floating-point noise)."""
    return int(min(n, max(1, math.ceil(round(anchor_percent / 100.0 * n, 9)))))


def mavos_schedule(
    W: np.ndarray,
    phi: np.ndarray | None = None,
    c: np.ndarray | None = None,
    *,
    strategy: str = "mavos",
    alpha: float | None = None,
    anchor_percent: float = 30.0,
    successors_per_round: int = 20,
    coverage: str = "SE",
    schedulable=None,
    s_tilde_from: str = "score",
) -> Schedule:
    """Greedy MaVOS view scheduling (or an ablation variant) of the views of a co-visibility graph.

    W: [N,N] co-visibility counts; phi: [N,d] spectral coordinates (needed for coverage "SE");
    c: [N] cumulative counts (default: W.sum(1)); schedulable: bool mask or index list of the views
    to schedule (default: the largest connected component of W); the others are "excluded".
    """
    alpha, K, M = _validate(strategy, alpha, anchor_percent, successors_per_round, coverage)
    if s_tilde_from not in S_TILDE_FROM:
        raise ValueError(f"s_tilde_from: {s_tilde_from!r} is not one of {S_TILDE_FROM}")
    W = check_graph(W)
    N = W.shape[0]
    c = W.sum(1) if c is None else np.asarray(c, dtype=np.float64).reshape(-1)
    if c.shape != (N,) or not np.all(np.isfinite(c)):
        raise ValueError(f"c: expected {N} finite values, got shape {c.shape}")
    if schedulable is None:
        mask = np.zeros(N, dtype=bool)
        if N:
            mask[largest_component(W)] = True
    else:
        s = np.asarray(schedulable)
        if s.dtype == bool:
            if s.shape != (N,):
                raise ValueError(f"schedulable: expected a bool mask of length {N}")
            mask = s.copy()
        else:
            mask = np.zeros(N, dtype=bool)
            mask[s.astype(np.int64)] = True
    if phi is not None:
        phi = np.asarray(phi, dtype=np.float64).reshape(N, -1)
        if not np.all(np.isfinite(phi[mask])):
            raise ValueError("phi: NaN or infinite spectral coordinates among the schedulable views")
        phi = np.where(np.isfinite(phi), phi, 0.0)
    dist = coverage_distances(W, phi, coverage)

    idx = np.flatnonzero(mask)
    n = len(idx)
    n_anchor = n_anchors_for(n, K) if n else 0
    # round sizes: anchors, then M per round, the last takes the rest
    if strategy == "uniform":
        sizes = [n] if n else []
    else:
        sizes = [n_anchor] if n else []
        rest = n - n_anchor
        while rest > 0:
            sizes.append(min(M, rest))
            rest -= sizes[-1]
    R = len(sizes)

    role = ["excluded"] * N
    rnd = np.full(N, -1, dtype=np.int64)
    order = np.full(N, -1, dtype=np.int64)
    S = np.zeros(N)
    Lv = np.zeros(N)
    Cv = np.zeros(N)
    L_raw_v = np.zeros(N)
    C_raw_v = np.zeros(N)
    picks: list[int] = []
    in_O = np.zeros(N, dtype=bool)
    # running sums / minima over O, maintained incrementally
    L_run = np.zeros(N)
    C_run = np.full(N, np.inf)

    pick_no = 0
    ranges = None  # (min, max) of L_raw and C_raw over the last multi-candidate set
    for r, size in enumerate(sizes):
        for _ in range(size):
            cand = idx[~in_O[idx]]
            if not picks:  # the seed: argmax c, recorded with S = L = C = 1
                Lc = (c[cand] == c[cand].max()).astype(np.float64)
                Cc = np.ones(len(cand))
                Lraw, Craw = c[cand], np.zeros(len(cand))
            else:
                Lraw, Craw = L_run[cand], C_run[cand]
                if len(cand) == 1 and ranges is not None:  # forced pick: reuse the last candidates' ranges
                    Lc, Cc = normalise(Lraw, ranges[0]), normalise(Craw, ranges[1])
                else:
                    Lc, Cc = normalise(Lraw), normalise(Craw)
                    ranges = ((Lraw.min(), Lraw.max()), (Craw.min(), Craw.max()))
            # uniform: one round, the pick order only lists the views (by coverage, as fps), so that
            # nothing it writes depends on alpha, K or M (which it does not use)
            Sc = Cc if strategy in ("fps", "uniform") else alpha * Lc + (1.0 - alpha) * Cc
            # first maximum: lowest view index (cand is sorted); the first pick is argmax c
            k = int(np.argmax(Lc if not picks else Sc))
            v = int(cand[k])
            picks.append(v)
            in_O[v] = True
            role[v] = "anchor" if r == 0 else f"round{r}"
            rnd[v], order[v] = r, pick_no
            S[v], Lv[v], Cv[v] = Sc[k], Lc[k], Cc[k]
            L_raw_v[v], C_raw_v[v] = Lraw[k], Craw[k]
            L_run += W[v]
            C_run = np.minimum(C_run, dist[v])
            pick_no += 1

    s_tilde_rounds = np.zeros((R, N))
    optimised = np.zeros((R, N), dtype=bool)
    for r in range(R):
        views = np.flatnonzero((rnd >= 0) & (rnd <= r))
        optimised[r, views] = True
        if strategy == "uniform":
            s_tilde_rounds[r, views] = 1.0
        elif s_tilde_from == "rank":  # earlier pick = more optimisable; evenly spaced in [0, 1]
            ranks = np.argsort(np.argsort(order[views], kind="stable"), kind="stable")
            s_tilde_rounds[r, views] = 1.0 - ranks / max(len(views) - 1, 1) if len(views) > 1 else 1.0
        else:
            s_tilde_rounds[r, views] = normalise(S[views], tie=1.0)
    s_tilde = np.zeros(N)
    for v in picks:
        s_tilde[v] = s_tilde_rounds[rnd[v], v]

    settings = {
        "strategy": strategy,
        "alpha": alpha if strategy == "mavos" else None,
        "anchor_percent": K if strategy != "uniform" else None,
        "successors_per_round": M if strategy != "uniform" else None,
        "coverage": coverage,
        "s_tilde_from": s_tilde_from if strategy != "uniform" else "constant 1 (uniform)",
        "round_sizes": sizes,
        "n_schedulable": n,
    }
    out = Schedule(
        role, rnd, order, S, Lv, Cv, L_raw_v, C_raw_v, s_tilde, s_tilde_rounds, optimised, picks, R,
        sizes[0] if sizes else 0, mask, settings,
    )
    for a in (S, Lv, Cv, s_tilde, s_tilde_rounds):
        assert np.all(np.isfinite(a)), "internal error: non-finite MaVOS score"
    return out
