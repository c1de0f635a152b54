"""covisibility: the co-visibility graph of the views.

``W[i, j] = n_ij``, the number of verified inlier matches of pair (i, j) (symmetric, zero
diagonal); pairs below ``min_inliers`` get ``n_ij := 0``. ``c_i = sum_j W_ij`` is the cumulative
count. Connected components of the graph W > 0, largest first. The maths: ``manifoldneus/scheduling/mavos.py``.

Outputs:

- ``covisibility.zarr``: ``W`` float64 [N,N], ``c`` float64 [N], ``component`` int32 [N]
  (label of each view's component, 0 = the largest), ``in_largest`` bool [N].
- ``components.json``: ``{"n_components", "components": [[view indices], ...] (largest first,
  each sorted), "component_names": [[view names], ...], "largest": [names], "outside_largest":
  [names], "isolated": [names of views with no edge]}``.
- ``covisibility.png`` (heat map of W) and ``graph.png`` (views on a circle or at their
  spectral coordinates, edge width ~ n_ij).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts
from manifoldneus.scheduling import mavos
from manifoldneus.config import param
from manifoldneus.data.io import save_figure, save_json


@dataclass
class Params:
    """Section `covisibility` of params.yaml."""

    min_inliers: int = param(15, "Pairs with fewer verified inliers get n_ij = 0 (0 keeps every pair)", lo=0)
    layout: str = param("spectral", "Node layout of graph.png", choices=["spectral", "circle"])


UPSTREAM = ("matching",)
SECTIONS = ("covisibility",)
OUTPUTS = (artifacts.COVISIBILITY, artifacts.COMPONENTS, "covisibility.png", "graph.png")


# --------------------------------------------------------------------------- plain functions


def spectral_layout(W: np.ndarray) -> np.ndarray:
    """2-D node positions: the first two spectral coordinates (:func:`mavos.spectral_embedding`) of
    each component, components side by side; a small circle for components of fewer than 4 views."""
    pos = circle_layout(len(W))
    x_off = 0.0
    for idx in mavos.connected_components(W) if len(W) else []:
        if len(idx) >= 4:
            p = mavos.spectral_embedding(W, d=2, component=idx).phi[idx]
            p = p - p.mean(0)
            p = p / max(np.abs(p).max(), 1e-12)
        else:
            p = circle_layout(len(idx)) * (0.3 if len(idx) > 1 else 0.0)
        pos[idx] = p + np.array([x_off, 0.0])
        x_off += 2.5
    return pos


def circle_layout(n: int) -> np.ndarray:
    a = 2 * np.pi * np.arange(n) / max(n, 1)
    return np.stack([np.cos(a), np.sin(a)], 1)


def plot_heatmap(W: np.ndarray, names: list[str], title: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(W)
    fig, ax = plt.subplots(figsize=(7, 6))
    im = ax.imshow(W, cmap="viridis", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="verified inliers n_ij")
    step = max(1, n // 25)
    ticks = np.arange(0, n, step)
    ax.set_xticks(ticks)
    ax.set_yticks(ticks)
    ax.set_xticklabels([names[t] for t in ticks], rotation=90, fontsize=6)
    ax.set_yticklabels([names[t] for t in ticks], fontsize=6)
    ax.set_title(title or "co-visibility W")
    return fig


def plot_graph(W: np.ndarray, names: list[str], pos: np.ndarray, labels: np.ndarray, title: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    n = len(W)
    fig, ax = plt.subplots(figsize=(7, 7))
    iu, ju = np.nonzero(np.triu(W, 1))
    if len(iu):
        w = W[iu, ju]
        segs = np.stack([pos[iu], pos[ju]], 1)
        lw = 0.2 + 4.0 * w / w.max()
        lc = LineCollection(segs, linewidths=lw, colors="tab:blue", alpha=0.35)
        ax.add_collection(lc)
    c = W.sum(1)
    size = 30 + 170 * (c / c.max() if c.max() > 0 else np.zeros(n))
    colors = np.where(labels == 0, "tab:orange", "tab:red")
    ax.scatter(pos[:, 0], pos[:, 1], s=size, c=colors, zorder=3, edgecolors="k", linewidths=0.5)
    for v in range(n):
        ax.annotate(names[v], pos[v], fontsize=6, ha="center", va="center", zorder=4)
    ax.set_aspect("equal")
    ax.autoscale()
    ax.axis("off")
    ax.set_title(title or "co-visibility graph (edge width ~ n_ij; red = outside the largest component)")
    return fig


# --------------------------------------------------------------------------- stage


def run(ctx) -> None:
    p: Params = ctx.params
    arrays, attrs = artifacts.load_matches(ctx.input("matching"), ["pairs", "n_inliers"])
    names = list(attrs["names"])
    n = len(names)

    W = mavos.covisibility_matrix(n, arrays["pairs"], arrays["n_inliers"], p.min_inliers)
    if not W.any():
        raise RuntimeError(f"no pair of the {n} views has {p.min_inliers} or more verified matches: the photos do not "
                           "overlap (or are identical, or featureless); take photos that see the object from nearby "
                           "viewpoints, or lower covisibility.min_inliers")
    c = W.sum(1)
    comp_idx = mavos.connected_components(W)
    labels = mavos.component_labels(W)
    n_comp = len(comp_idx)
    comps = [[names[v] for v in idx] for idx in comp_idx]
    outside = [names[v] for v in range(n) if labels[v] != 0]
    isolated = [names[v] for v in range(n) if c[v] == 0]

    artifacts.save_covisibility(
        ctx.out,
        {"W": W, "c": c, "component": labels.astype(np.int32), "in_largest": labels == 0},
        attrs={"names": names, "min_inliers": p.min_inliers},
    )
    save_json(
        Path(ctx.out) / artifacts.COMPONENTS,
        {
            "n_components": n_comp,
            "components": comp_idx,
            "component_names": comps,
            "largest": comps[0] if comps else [],
            "outside_largest": outside,
            "isolated": isolated,
        },
    )
    save_figure(Path(ctx.out) / "covisibility.png", plot_heatmap(W, names, f"{ctx.scene}: co-visibility W (n_ij >= {p.min_inliers})"))
    pos = spectral_layout(W) if p.layout == "spectral" else circle_layout(n)
    save_figure(Path(ctx.out) / "graph.png", plot_graph(W, names, pos, labels, f"{ctx.scene}: co-visibility graph ({p.layout} layout)"))

    if n_comp > 1:
        ctx.log.warning(
            f"the co-visibility graph is disconnected: {n_comp} components; {len(outside)} view(s) outside the "
            f"largest component ({len(comps[0])} views): {', '.join(outside)}"
        )
    edges = int((np.triu(W, 1) > 0).sum())
    ctx.log.info(f"{n} views, {edges} edges, {n_comp} component(s), c_i in [{c.min():.0f}, {c.max():.0f}]")
    ctx.metrics["n_views"] = n
    ctx.metrics["n_edges"] = edges
    ctx.metrics["n_components"] = n_comp
    ctx.metrics["largest_component_size"] = len(comps[0]) if comps else 0
    ctx.metrics["outside_largest"] = ", ".join(outside)
    ctx.metrics["c_min"] = float(c.min()) if n else 0.0
    ctx.metrics["c_mean"] = float(c.mean()) if n else 0.0
    ctx.metrics["c_max"] = float(c.max()) if n else 0.0
