"""schedule: MaVOS view scheduling (METHOD.md stage 6), or an ablation variant.

Greedy picking of anchors (ceil(K% n) views, starting from the view of largest c_i) and successor
rounds of M views (the last round takes the rest) by ``S_i = alpha L_i + (1 - alpha) C_i``;
variants: coverage ``SE`` (spectral) | ``E`` (rows of W), strategy ``mavos`` | ``fps`` | ``uniform``.
Every definition (normalisation, ties, S~, what uniform/fps record): ``manifoldneus/scheduling/mavos.py``.
Views outside the largest co-visibility component and the views held out for novel-view evaluation
(section `split`) are not scheduled (role ``excluded``): K % counts the views that are trained.
This stage never reads ground truth: its figure is drawn in spectral coordinates.

Outputs:
- ``schedule.zarr``: ``round`` int64 [N] (0 anchors, r >= 1 successor round, -1 excluded),
  ``order`` int64 [N] (global pick order, -1 excluded), ``S``, ``L``, ``C``, ``L_raw``, ``C_raw``,
  ``s_tilde`` float64 [N]; ``s_tilde_rounds`` float64 [R,N] and ``optimised`` bool [R,N] (views
  optimised in round r = all views scheduled in rounds 0..r); ``schedulable`` bool [N].
- ``schedule.json``: settings, per view (name, role, round, order, S, L, C, S~), rounds (views
  added per round, in pick order), n_rounds, anchors, whether the anchors form one connected
  co-visibility cluster.
- ``schedule.png``: views in spectral coordinates coloured by role with their pick order, and the
  ranking bar chart of S (supplement Fig. A6 style).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.scheduling import mavos
from manifoldneus.config import holdout_mask, param
from manifoldneus.data.scenes import SceneError


@dataclass
class Params:
    """Section `schedule` of params.yaml."""

    strategy: str = param("mavos", "mavos (greedy S = alpha L + (1-alpha) C) | fps (farthest-point sampling) | "
                                   "uniform (all views at once: the NeuS-BARF baseline)",
                          choices=list(mavos.STRATEGIES))
    alpha: float = param(0.65, "Balance of local constraint L (1) vs coverage C (0)", lo=0.0, hi=1.0)
    anchor_percent: float = param(30.0, "K: anchors = ceil(K% of the schedulable views)", lo=1e-9, hi=100.0)
    successors_per_round: int = param(20, "M: views added per successor round (the last round takes the rest)", lo=1)
    coverage: str = param("SE", "Coverage distance: SE (spectral embedding) | E (Euclidean on rows of W)",
                          choices=list(mavos.COVERAGES))
    s_tilde_from: str = param("score", "S~ from the score at pick time, min-max normalised per round (METHOD.md) | "
                                       "rank: from the pick order (variant; see manifoldneus/scheduling/mavos.py)",
                              choices=list(mavos.S_TILDE_FROM))


UPSTREAM = ("ingest", "covisibility", "spectral")
SECTIONS = ("schedule", "split")
OUTPUTS = (artifacts.SCHEDULE, artifacts.SCHEDULE_META, artifacts.SCHEDULE_PLOT)

ROUND_COLOURS = ["#8c510a", "#1b9e77", "#969696", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d"]


def _colour(r: int) -> str:
    return ROUND_COLOURS[r % len(ROUND_COLOURS)] if r >= 0 else "white"


def _label(r: int) -> str:
    return "anchors" if r == 0 else (f"round {r}" if r > 0 else "excluded")


def plot_schedule(sched: mavos.Schedule, phi: np.ndarray, W: np.ndarray, path, title: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Patch

    N = len(sched.round)
    d = phi.shape[1] if phi.ndim == 2 else 0
    xy = np.zeros((N, 2))
    xy[:, : min(d, 2)] = phi[:, : min(d, 2)]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(15, 6.2), gridspec_kw={"width_ratios": [1.0, 1.35]})

    # co-visibility edges, drawn faintly (width ~ n_ij), among scheduled views
    sch = np.flatnonzero(sched.schedulable)
    ii, jj = np.nonzero(np.triu(W[np.ix_(sch, sch)], 1))
    if len(ii):
        wmax = W.max()
        segs = np.stack([xy[sch[ii]], xy[sch[jj]]], 1)
        lw = 0.2 + 1.8 * W[sch[ii], sch[jj]] / wmax
        ax.add_collection(LineCollection(segs, colors="0.75", linewidths=lw, zorder=0))
    # anchors' internal edges darker: shows whether the anchor set is one cluster
    anc = np.array(sched.anchors, dtype=np.int64)
    if len(anc) > 1:
        ai, aj = np.nonzero(np.triu(W[np.ix_(anc, anc)], 1))
        if len(ai):
            segs = np.stack([xy[anc[ai]], xy[anc[aj]]], 1)
            ax.add_collection(LineCollection(segs, colors=_colour(0), linewidths=0.8, alpha=0.6, zorder=1))
    for r in range(sched.n_rounds):
        v = np.flatnonzero(sched.round == r)
        ax.scatter(xy[v, 0], xy[v, 1], s=150, c=_colour(r), edgecolors="k", linewidths=0.6, zorder=2)
    for i in range(N):
        if sched.round[i] >= 0:
            ax.annotate(str(int(sched.order[i]) + 1), xy[i], ha="center", va="center", fontsize=7,
                        color="white" if sched.round[i] != 2 else "black", zorder=3)
            ax.annotate(f"v{i}", xy[i], xytext=(6, -9), textcoords="offset points", fontsize=6, color="0.35")
    handles = [Patch(facecolor=_colour(r), edgecolor="k", label=f"{_label(r)} ({int((sched.round == r).sum())})")
               for r in range(sched.n_rounds)]
    n_exc = int((sched.round < 0).sum())
    if n_exc:
        handles.append(Patch(facecolor="white", edgecolor="k", label=f"excluded ({n_exc}, not drawn)"))
    # a fixed corner: loc="best" scores candidate positions against all ~2N annotations, a large share of the
    # figure's time
    ax.legend(handles=handles, fontsize=8, loc="upper right")
    ax.set_xlabel("phi_1")
    ax.set_ylabel("phi_2")
    ax.set_title("views in spectral coordinates; number = pick order", fontsize=9)
    ax.autoscale()

    picks = sched.picks
    x = np.arange(len(picks))
    bx.bar(x, sched.S[picks], color=[_colour(int(sched.round[i])) for i in picks], edgecolor="k", linewidth=0.4)
    bx.plot(x, sched.s_tilde[picks], "o", color="crimson", ms=3.5, label="S~ (normalised within its round)")
    bx.set_xticks(x)
    bx.set_xticklabels([str(i) for i in picks], rotation=90, fontsize=6)
    bx.set_xlabel("view (in pick order)")
    bx.set_ylabel("S at pick time")
    bx.set_ylim(0, 1.05)
    bx.legend(fontsize=8, loc="upper right")
    bx.set_title("MaVOS ranking: score at pick time", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    io.save_figure(path, fig)


MIN_ANCHORS = 2  # the anchors' initialisation from matches needs a pair


def run(ctx) -> None:
    p = ctx.params
    meta = artifacts.load_views_meta(ctx.input("ingest"))
    names = meta["names"]
    cov = artifacts.load_covisibility(ctx.input("covisibility"), ["W", "c"])
    W = np.asarray(cov["W"], np.float64)
    c = np.asarray(cov["c"], np.float64).reshape(-1)
    spec = io.load_arrays(ctx.input("spectral") / artifacts.SPECTRAL, ["phi", "in_component"])
    phi, in_comp = spec["phi"], spec["in_component"].astype(bool)
    N = W.shape[0]
    if len(names) != N or len(phi) != N:
        raise ValueError(f"view count mismatch: {len(names)} names, W {W.shape}, phi {phi.shape}")

    split = ctx.section("split")
    held_out = holdout_mask(N, split, meta.get("has_cameras", True))
    if split.holdout_every and not held_out.any():
        ctx.log.info("no view held out: the input has no cameras to score them (split.holdout_without_cameras)")
    sched = mavos.mavos_schedule(
        W, phi, c, strategy=p.strategy, alpha=p.alpha, anchor_percent=p.anchor_percent,
        successors_per_round=p.successors_per_round, coverage=p.coverage, schedulable=in_comp & ~held_out,
        s_tilde_from=p.s_tilde_from,
    )
    excluded = np.flatnonzero(~in_comp | held_out).tolist()
    outside = np.flatnonzero(~in_comp).tolist()
    if len(sched.anchors) < MIN_ANCHORS:  # said here, before any training, not when the anchors start
        n_sched = int((in_comp & ~held_out).sum())
        need = math.ceil(100.0 * MIN_ANCHORS / n_sched) if n_sched >= MIN_ANCHORS else None
        raise SceneError(
            f"{ctx.scene}: {len(sched.anchors)} anchor view(s) of {n_sched} schedulable ({N} views, {int(held_out.sum())} "
            f"held out by split.holdout_every={ctx.section('split').holdout_every}, {len(outside)} outside the "
            f"largest co-visibility component); the anchors' initialisation needs at least {MIN_ANCHORS}: "
            + (f"--set schedule.anchor_percent={need}" if need else "add photos")
            + (" or --set split.holdout_every=0" if held_out.any() else ""))
    if outside:
        ctx.log.warning("views %s are outside the largest co-visibility component: not scheduled (role 'excluded'); "
                        "later stages must skip them", [names[i] for i in outside])
    ctx.log.info("%d views held out for novel-view evaluation are not scheduled", int(held_out.sum()))
    anchors = sched.anchors
    connected = mavos.is_connected_subset(W, anchors)
    n_clusters = len(mavos.connected_components(W[np.ix_(anchors, anchors)])) if anchors else 0
    bottleneck = mavos.bottleneck_weight(W, anchors) if len(anchors) > 1 else None
    rounds = [sched.round_views(r) for r in range(sched.n_rounds)]
    ctx.log.info("%s/%s: %d anchors (%s, weakest spanning link %s matches), rounds %s", p.strategy, p.coverage,
                 len(anchors), "one connected cluster" if connected else f"{n_clusters} clusters", bottleneck,
                 [len(r) for r in rounds])

    io.save_arrays(ctx.out / artifacts.SCHEDULE, {
        "round": sched.round, "order": sched.order, "S": sched.S, "L": sched.L, "C": sched.C,
        "L_raw": sched.L_raw, "C_raw": sched.C_raw, "s_tilde": sched.s_tilde,
        "s_tilde_rounds": sched.s_tilde_rounds, "optimised": sched.optimised, "schedulable": sched.schedulable,
    }, attrs={"n_rounds": sched.n_rounds, "strategy": p.strategy, "coverage": p.coverage}, chunk_first=False)

    per_view = [{
        "view": i, "name": names[i], "role": sched.role[i], "round": int(sched.round[i]), "order": int(sched.order[i]),
        "S": float(sched.S[i]), "L": float(sched.L[i]), "C": float(sched.C[i]),
        "L_raw": float(sched.L_raw[i]), "C_raw": float(sched.C_raw[i]), "s_tilde": float(sched.s_tilde[i]),
        "c": float(c[i]),
    } for i in range(N)]
    io.save_json(ctx.out / artifacts.SCHEDULE_META, {
        "settings": sched.settings,
        "n_views": N,
        "n_rounds": sched.n_rounds,
        "round_sizes": [len(r) for r in rounds],
        "rounds": rounds,
        "rounds_names": [[names[i] for i in r] for r in rounds],
        "anchors": anchors,
        "n_anchors": len(anchors),
        "anchors_connected": bool(connected),
        "anchor_clusters": n_clusters,
        "anchor_bottleneck_matches": bottleneck,
        "anchors_connected_definition": "the subgraph of W (edges n_ij > 0) induced by the anchors is connected; "
                                        "anchor_bottleneck_matches = weakest link of its maximum spanning tree",
        "excluded_views": excluded,
        "held_out_views": np.flatnonzero(held_out).tolist(),
        "picks": sched.picks,
        "s_tilde_definition": ("S at pick time, min-max normalised over all views optimised in that round "
                               "(views scheduled in rounds 0..r); ties -> 1; uniform -> 1") if p.s_tilde_from == "score"
                              else ("1 - rank / (n_r - 1) by pick order over all views optimised in that round "
                                    "(views scheduled in rounds 0..r); uniform -> 1"),
        "views": per_view,
    })
    plot_schedule(sched, phi, W, ctx.out / artifacts.SCHEDULE_PLOT,
                  title=f"{ctx.scene}: {p.strategy}-{p.coverage}"
                        + (f", alpha = {p.alpha}" if p.strategy == "mavos" else "")
                        + (f", K = {p.anchor_percent:g}%, M = {p.successors_per_round}" if p.strategy != "uniform" else "")
                        + "; anchors "
                        + ("form one connected cluster" if connected else f"form {n_clusters} clusters")
                        + (f" (weakest spanning link {bottleneck:g} matches)" if bottleneck else ""))
    ctx.metrics.update(n_anchors=len(anchors), anchors_connected=bool(connected), anchor_clusters=n_clusters,
                       anchor_bottleneck_matches=bottleneck,
                       n_rounds=sched.n_rounds, round_sizes=[len(r) for r in rounds], n_excluded=len(excluded))
