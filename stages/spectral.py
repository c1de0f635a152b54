"""spectral: spectral embedding of the co-visibility graph (METHOD.md stage 5).

Normalised Laplacian ``L = I - D^-1/2 W D^-1/2`` of the largest connected component of W, the
eigenvectors of its ``d`` smallest non-trivial eigenvalues, rows scaled by ``D^-1/2``: one
coordinate ``phi_i`` per view (maths and conventions: ``manifoldneus/scheduling/mavos.py``).

Outputs:
- ``spectral.zarr``: ``phi`` float64 [N,d] (0 for views outside the component), ``eigenvalues``
  float64 [d], ``in_component`` bool [N], ``c`` float64 [N] (cumulative counts, copied).
- ``spectral.json``: d requested / used, eigenvalues, solver, component, excluded views.
- ``spectral.png``: the first 2-3 coordinates, coloured by c_i.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.scheduling import mavos
from manifoldneus.config import param


@dataclass
class Params:
    """Section `spectral` of params.yaml."""

    d: int = param(8, "Embedding dimension: eigenvectors of the d smallest non-trivial eigenvalues "
                      "(capped at the component size - 1, with a note in the log)", lo=1)
    dense_max: int = param(mavos.DENSE_MAX, "Up to this many views use a dense eigensolver (scipy.linalg.eigh), "
                                            "above it scipy.sparse.linalg.eigsh", lo=2)


UPSTREAM = ("covisibility",)
SECTIONS = ("spectral",)
OUTPUTS = (artifacts.SPECTRAL, "spectral.json", "spectral.png")


def load_covisibility(cov_dir):
    """(W float64 [N,N], c float64 [N], components from components.json or None)."""
    arrays = artifacts.load_covisibility(cov_dir, ["W", "c"])
    comps = None
    if (cov_dir / artifacts.COMPONENTS).is_file():
        comps = io.load_json(cov_dir / artifacts.COMPONENTS)
        if isinstance(comps, dict):
            comps = comps.get("components")
    return np.asarray(arrays["W"], np.float64), np.asarray(arrays["c"], np.float64).reshape(-1), comps


def plot_embedding(phi: np.ndarray, c: np.ndarray, in_comp: np.ndarray, eigenvalues: np.ndarray, path, title=""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    N, d = phi.shape
    pairs = [(0, 1), (0, 2)] if d >= 3 else [(0, 1)]
    # fixed spacing instead of layout="constrained": its solver took about half of this figure's time
    fig, axes = plt.subplots(1, len(pairs) + 1, figsize=(5.8 * (len(pairs) + 1), 4.8))
    fig.subplots_adjust(left=0.04, right=0.99, wspace=0.42, top=0.88)
    idx = np.flatnonzero(in_comp)
    for ax, (a, b) in zip(axes, pairs):
        x = phi[idx, a] if d > a else np.zeros(len(idx))
        y = phi[idx, b] if d > b else np.zeros(len(idx))
        sc = ax.scatter(x, y, c=c[idx], cmap="viridis", s=40, edgecolors="k", linewidths=0.4)
        for k, i in enumerate(idx):
            ax.annotate(str(i), (x[k], y[k]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel(f"phi_{a + 1}")
        ax.set_ylabel(f"phi_{b + 1}")
        ax.set_title(f"spectral coordinates {a + 1} vs {b + 1}", fontsize=9)
        fig.colorbar(sc, ax=ax, label="c_i", fraction=0.06, pad=0.02)
    ax = axes[-1]
    if len(eigenvalues):
        ax.plot(np.arange(1, len(eigenvalues) + 1), eigenvalues, "o-")
    ax.set_xlabel("k (non-trivial)")
    ax.set_ylabel("eigenvalue of L")
    ax.set_title("normalised Laplacian spectrum", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    io.save_figure(path, fig)


def run(ctx) -> None:
    p = ctx.params
    W, c, comps_file = load_covisibility(ctx.input("covisibility"))
    N = W.shape[0]
    comps = mavos.connected_components(W)
    if comps_file is not None and comps_file and sorted(comps_file[0]) != comps[0]:
        ctx.log.warning("components.json's largest component differs from W's; using W's (%d views)", len(comps[0]))
    emb = mavos.spectral_embedding(W, d=p.d, component=comps[0], dense_max=p.dense_max)
    if emb.d < p.d:
        ctx.log.info("d = %d capped to %d (the component has %d views)", p.d, emb.d, len(emb.component))
    excluded = np.flatnonzero(~emb.in_component).tolist()
    if excluded:
        ctx.log.warning(
            "%d view(s) outside the largest co-visibility component are excluded from the embedding "
            "and from scheduling: %s", len(excluded), excluded)
    if not np.all(np.isfinite(emb.phi)):
        raise RuntimeError("spectral embedding produced non-finite coordinates")
    io.save_arrays(ctx.out / artifacts.SPECTRAL, {
        "phi": emb.phi, "eigenvalues": emb.eigenvalues, "in_component": emb.in_component, "c": c,
    }, attrs={"d": emb.d, "d_requested": p.d}, chunk_first=False)
    io.save_json(ctx.out / "spectral.json", {
        "n_views": N,
        "d_requested": p.d,
        "d": emb.d,
        "solver": emb.solver,
        "eigenvalues": emb.eigenvalues,
        "trivial_eigenvalue": emb.trivial_eigenvalue,
        "component": emb.component,
        "excluded_views": excluded,
        "n_components": len(comps),
        "definition": "L = I - D^-1/2 W D^-1/2 on the largest component; phi = D^-1/2 u_k, k = 1..d; "
                      "sign: largest-|entry| positive (manifoldneus/scheduling/mavos.py)",
    })
    plot_embedding(emb.phi, c, emb.in_component, emb.eigenvalues, ctx.out / "spectral.png",
                   title=f"{ctx.scene}: spectral embedding (d = {emb.d}), colour = c_i")
    ctx.metrics.update(d=emb.d, n_in_component=int(emb.in_component.sum()), n_excluded=len(excluded),
                       fiedler_value=float(emb.eigenvalues[0]) if emb.d else None)
