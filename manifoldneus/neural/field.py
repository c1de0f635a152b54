"""Neural SDF + colour fields behind one interface (chosen by ``FieldParams.kind``).

* ``mlp``: the NeuS field. Fourier positional encoding (``pos_bands`` frequencies 2^k, k < L, plus
  the raw input), an MLP with a skip connection and geometric initialisation (a sphere of
  radius ``init_radius``), colour MLP on (x, normal, Fourier view direction, feature) as NeuS.
* ``grid``: CPU-fast. ``grid_levels`` dense 3D feature grids (trilinear, ``grid_encoding``) with
  resolutions growing geometrically from ``grid_min_res`` to ``grid_max_res`` over an axis-aligned
  box, a tiny SDF decoder (sdf = |x| - init_radius + decoder residual, so the initial surface is a
  sphere too) and a tiny colour decoder on (feature, view direction); no per-sample normal.

Both accept ``band_weights`` [N, L] (or [L]): multiplicative weights of the L Fourier bands
(``mlp``) or grid levels (``grid``), 1 = fully on, so a coarse-to-fine gate (BARF-style, per
view) plugs in without touching the field. ``field.n_bands`` is L.

Both carry NeuS's learned inverse standard deviation: ``inv_s() = exp(10 * variance)``.
Gradients of the SDF (normals / Eikonal) come from autograd (``analytic``) or from tetrahedral
finite differences (``fd``, 4 SDF evaluations, as Instant-NSR / Neuralangelo; also a smoothness
regulariser for grids); ``gradient_mode = "auto"`` picks analytic for ``mlp``, fd for ``grid``.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from manifoldneus.config import param
from manifoldneus.neural.grid_encoding import encode


@dataclass
class FieldParams:
    """Section `field`: the neural SDF / colour field."""

    kind: str = param("grid", "Field variant: 'grid' (dense multi-resolution grids, CPU-fast) or 'mlp' (NeuS Fourier MLP)",
                      choices=["grid", "mlp"])
    init_radius: float = param(0.5, "Radius of the initial sphere (geometric initialisation)", lo=0.05, hi=1.0)
    init_variance: float = param(0.3, "Initial NeuS variance parameter v (inv_s = exp(10 v))", lo=-1.0, hi=1.0)
    feature_dim: int = param(15, "Geometry feature passed from the SDF network to the colour network", lo=1)
    dir_bands: int = param(4, "Fourier bands of the view-direction encoding", lo=0, hi=10)
    view_cosine: bool = param(False, "grid: the colour decoder also reads the cosine between the view direction and "
                              "the SDF's normal where the ray meets the surface (the shading under a light that "
                              "moves with the camera, as DTU's, with no bands of the view direction; 0 without "
                              "importance samples, which estimate that point). The colour's loss does not reach the "
                              "SDF through that normal")
    gradient_mode: str = param("auto", "SDF gradients: 'analytic' (autograd), 'fd' (tetrahedral finite differences) or 'auto'",
                               choices=["auto", "analytic", "fd"])
    fd_eps: float = param(0.0, "Finite-difference step (scene units); 0 = half the finest grid cell (grid) or 1e-3 (mlp)",
                          lo=0.0, hi=0.2)
    # --- mlp
    pos_bands: int = param(6, "mlp: Fourier bands of the position encoding (the gated bands)", lo=0, hi=12)
    mlp_width: int = param(256, "mlp: hidden width of the SDF network", lo=8)
    mlp_depth: int = param(8, "mlp: hidden layers of the SDF network", lo=2)
    mlp_skip: int = param(4, "mlp: layer index of the skip connection (-1 = none)", lo=-1)
    color_width: int = param(256, "mlp: hidden width of the colour network", lo=8)
    color_depth: int = param(4, "mlp: hidden layers of the colour network", lo=1)
    weight_norm: bool = param(True, "mlp: weight normalisation (as NeuS)")
    # --- grid
    grid_levels: int = param(6, "grid: number of resolution levels (the gated bands)", lo=1, hi=16)
    grid_min_res: int = param(16, "grid: resolution of the coarsest level", lo=2)
    grid_max_res: int = param(128, "grid: resolution of the finest level", lo=2, hi=2048)
    grid_hash_log2: int = param(0, "grid: a level with more than 2^this cells is a hash table of 2^this rows "
                                "(instant-NGP's spatial hash: fine levels at a fixed memory; colliding cells share "
                                "a row); 0 = every level dense", lo=0, hi=24)
    grid_channels: int = param(4, "grid: feature channels per level", lo=1, hi=32)
    grid_init_std: float = param(1e-3, "grid: std of the initial grid features", lo=0.0)
    grid_kernel: str = param("auto", "grid: look-up kernel: 'fused' (compiled CPU kernel, about half grid_sample's CPU time), "
                             "'torch' (grid_sample, any device) or 'auto' (fused on the CPU when it builds)",
                             choices=["auto", "fused", "torch"])
    decoder_width: int = param(64, "grid: hidden width of the SDF and colour decoders", lo=8)
    decoder_depth: int = param(1, "grid: hidden layers of the SDF decoder", lo=1)
    color_decoder_depth: int = param(2, "grid: hidden layers of the colour decoder", lo=1)


# ----------------------------------------------------------------------------- helpers


def fourier_encode(x: torch.Tensor, n_bands: int, band_weights: torch.Tensor | None = None) -> torch.Tensor:
    """[N,D] -> [N, D + 2*D*n_bands]: x, then sin/cos(2^k x) per band k (NeuS layout per band).
    ``band_weights`` [N, n_bands] or [n_bands] scales the sin and cos of band k."""
    if n_bands == 0:
        return x
    freqs = 2.0 ** torch.arange(n_bands, device=x.device, dtype=x.dtype)  # [L]
    xb = x[:, None, :] * freqs[None, :, None]  # [N,L,D]
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], -1)  # [N,L,2D]
    if band_weights is not None:
        bw = band_weights.to(x.dtype)
        bw = bw[None, :, None] if bw.dim() == 1 else bw[:, :, None]
        enc = enc * bw
    return torch.cat([x, enc.reshape(x.shape[0], 2 * x.shape[1] * n_bands)], -1)  # explicit: N may be 0


TETRA = torch.tensor([[1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0]])


@functools.lru_cache(maxsize=None)
def _tetra_on(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return TETRA.to(device, dtype)


def _tetra(x: torch.Tensor) -> torch.Tensor:
    """TETRA on x's device and dtype, copied there once: a copy per call is a synchronisation on a GPU."""
    if torch.compiler.is_compiling():  # a compiled graph holds it as a constant
        return TETRA.to(x)
    return _tetra_on(x.device, x.dtype)


class FieldBase(nn.Module):
    """Common interface. Subclasses implement ``_sdf_feat`` and ``_color``."""

    n_bands: int = 0
    color_uses_normal: bool = False  # per-sample normals [N,3]
    color_uses_ray_normal: bool = False  # the normal where each sample's ray meets the surface [N,3]

    def __init__(self, p: FieldParams):
        super().__init__()
        self.p = p
        self.variance = nn.Parameter(torch.tensor(float(p.init_variance)))
        self.gradient_mode = p.gradient_mode
        self.fd_eps = p.fd_eps

    # -- NeuS inverse standard deviation
    def inv_s(self) -> torch.Tensor:
        return torch.exp(self.variance * 10.0).clamp(1e-6, 1e6)

    # -- interface
    def sdf(self, x: torch.Tensor, band_weights: torch.Tensor | None = None) -> torch.Tensor:
        """SDF at points [N,3] -> [N]."""
        return self._sdf_feat(x, band_weights)[0]

    def forward(self, x, dirs, band_weights=None, normals=None):
        """(sdf [N], rgb [N,3] in [0,1]) at points x [N,3] seen along unit dirs [N,3].
        ``normals`` [N,3] is required when ``color_uses_normal`` or ``color_uses_ray_normal``."""
        sdf, feat = self._sdf_feat(x, band_weights)
        return sdf, self._color(x, dirs, feat, normals)

    def resolved_gradient_mode(self) -> str:
        if self.gradient_mode != "auto":
            return self.gradient_mode
        return "fd" if self.p.kind == "grid" else "analytic"

    def default_fd_eps(self) -> float:
        return 1e-3

    def gradient_points(self, x: torch.Tensor, mode: str | None = None, create_graph: bool = True):
        """Split a gradient evaluation so it can share one batched field call with other points.
        Returns (points to evaluate [M,3], repeat factor k (band weights repeat k times),
        finish(sdf_at_points [M]) -> (grad [N,3], sdf [N]))."""
        mode = mode or self.resolved_gradient_mode()
        n = x.shape[0]
        if mode == "fd":
            eps = self.fd_eps if self.fd_eps > 0 else self.default_fd_eps()
            T = _tetra(x)
            pts = (x.detach()[None, :, :] + eps * T[:, None, :]).reshape(-1, 3)

            def finish(f):
                f = f.reshape(4, n)
                return (f[:, :, None] * T[:, None, :]).sum(0) / (4.0 * eps), f.mean(0)

            return pts, 4, finish
        xg = x.detach().requires_grad_(True)

        def finish(f):
            (g,) = torch.autograd.grad(f.sum(), xg, create_graph=create_graph)
            return g, f

        return xg, 1, finish

    def gradient(self, x: torch.Tensor, band_weights=None, create_graph: bool = True, mode: str | None = None):
        """SDF gradient at x [N,3] -> (grad [N,3], sdf [N]). fd: tetrahedral differences (the sdf
        returned is their mean, a second-order estimate); analytic: autograd."""
        mode = mode or self.resolved_gradient_mode()
        if mode == "fd":
            eps = self.fd_eps if self.fd_eps > 0 else self.default_fd_eps()
            T = _tetra(x)
            n = x.shape[0]
            xs = (x[None, :, :] + eps * T[:, None, :]).reshape(-1, 3)
            bw = None
            if band_weights is not None:
                bw = band_weights if band_weights.dim() == 1 else band_weights.repeat(4, 1)
            f = self.sdf(xs, bw).reshape(4, n)
            grad = (f[:, :, None] * T[:, None, :]).sum(0) / (4.0 * eps)
            return grad, f.mean(0)
        with torch.enable_grad():
            xg = x if x.requires_grad else x.detach().requires_grad_(True)
            f = self.sdf(xg, band_weights)
            (grad,) = torch.autograd.grad(f.sum(), xg, create_graph=create_graph)
        return grad, f

    def extra_repr(self) -> str:
        return f"kind={self.p.kind}, n_bands={self.n_bands}"


# ----------------------------------------------------------------------------- mlp


class MLPField(FieldBase):
    color_uses_normal = True

    def __init__(self, p: FieldParams):
        super().__init__(p)
        self.n_bands = p.pos_bands
        d_in = 3 + 6 * p.pos_bands
        W, D = p.mlp_width, p.mlp_depth
        dims = [d_in] + [W] * D + [1 + p.feature_dim]
        self.skip = p.mlp_skip
        self.d_in = d_in
        layers = []
        n_lin = len(dims) - 1
        for li in range(n_lin):
            out_dim = dims[li + 1] - d_in if (li + 1) == self.skip else dims[li + 1]
            lin = nn.Linear(dims[li], out_dim)
            # geometric initialisation (Atzmon & Lipman; NeuS layout)
            if li == n_lin - 1:
                nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(dims[li]), std=1e-4)
                nn.init.constant_(lin.bias, -p.init_radius)
            elif li == 0 and p.pos_bands > 0:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.constant_(lin.weight[:, 3:], 0.0)
                nn.init.normal_(lin.weight[:, :3], 0.0, math.sqrt(2) / math.sqrt(out_dim))
            elif li == self.skip and p.pos_bands > 0:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))
                nn.init.constant_(lin.weight[:, -(d_in - 3):], 0.0)
            else:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))
            if p.weight_norm:
                lin = nn.utils.parametrizations.weight_norm(lin)
            layers.append(lin)
        self.sdf_layers = nn.ModuleList(layers)
        self.act = nn.Softplus(beta=100)
        d_dir = 3 + 6 * p.dir_bands
        cdims = [3 + 3 + d_dir + p.feature_dim] + [p.color_width] * p.color_depth + [3]
        clayers = []
        for li in range(len(cdims) - 1):
            lin = nn.Linear(cdims[li], cdims[li + 1])
            if p.weight_norm:
                lin = nn.utils.parametrizations.weight_norm(lin)
            clayers.append(lin)
        self.color_layers = nn.ModuleList(clayers)

    def _sdf_feat(self, x, band_weights=None):
        inp = fourier_encode(x, self.p.pos_bands, band_weights)
        h = inp
        for li, lin in enumerate(self.sdf_layers):
            if li == self.skip:
                h = torch.cat([h, inp], -1) / math.sqrt(2)
            h = lin(h)
            if li < len(self.sdf_layers) - 1:
                h = self.act(h)
        return h[:, 0], h[:, 1:]

    def _color(self, x, dirs, feat, normals):
        if normals is None:
            raise ValueError("the mlp field's colour network needs normals")
        h = torch.cat([x, normals, fourier_encode(dirs, self.p.dir_bands), feat], -1)
        for li, lin in enumerate(self.color_layers):
            h = lin(h)
            if li < len(self.color_layers) - 1:
                h = F.relu(h)
        return torch.sigmoid(h)


# ----------------------------------------------------------------------------- grid


def level_resolutions(n_levels: int, r_min: int, r_max: int) -> list[int]:
    if n_levels == 1:
        return [r_max]
    b = math.exp((math.log(r_max) - math.log(r_min)) / (n_levels - 1))
    return [int(round(r_min * b**i)) for i in range(n_levels)]


class GridField(FieldBase):
    color_uses_normal = False

    def __init__(self, p: FieldParams):
        super().__init__(p)
        self.n_bands = p.grid_levels
        self.resolutions = level_resolutions(p.grid_levels, p.grid_min_res, p.grid_max_res)
        C = p.grid_channels
        # channel-last tables, dense [R,R,R,C] or hashed [T,C] (grid_encoding's convention)
        T = 2 ** p.grid_hash_log2 if p.grid_hash_log2 else None
        self.grids = nn.ParameterList(
            [nn.Parameter(torch.randn(*((T,) if T and r ** 3 > T else (r, r, r)), C) * p.grid_init_std)
             for r in self.resolutions]
        )
        # autograd gradients are differentiated again (Eikonal): only grid_sample's kernel allows it
        self.grid_kernel = "torch" if self.resolved_gradient_mode() == "analytic" else p.grid_kernel
        self.register_buffer("aabb", torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]))
        # the box's largest extent as a host float (the finite-difference step reads it every step: read
        # from the buffer, a synchronisation on a GPU); kept with the buffer by set_aabb and loading
        self._extent = 2.0
        self.register_load_state_dict_post_hook(_read_extent_after_load)
        d_feat = C * p.grid_levels + 3
        layers = []
        d = d_feat
        for _ in range(p.decoder_depth):
            layers.append(nn.Linear(d, p.decoder_width))
            d = p.decoder_width
        last = nn.Linear(d, 1 + p.feature_dim)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        layers.append(last)
        self.sdf_layers = nn.ModuleList(layers)
        d_dir = 3 + 6 * p.dir_bands
        cl = []
        self.color_uses_ray_normal = p.view_cosine
        d = p.feature_dim + d_dir + C * p.grid_levels + int(p.view_cosine)
        for _ in range(p.color_decoder_depth):
            cl.append(nn.Linear(d, p.decoder_width))
            d = p.decoder_width
        cl.append(nn.Linear(d, 3))
        self.color_layers = nn.ModuleList(cl)
        self._last_feats = None

    def set_aabb(self, lo, hi) -> None:
        """Box covered by the grids (points outside read zero features)."""
        self.aabb.copy_(torch.tensor(list(lo) + list(hi), dtype=self.aabb.dtype))
        self._read_extent()

    def _read_extent(self) -> None:
        self._extent = float((self.aabb[3:] - self.aabb[:3]).max())

    def default_fd_eps(self) -> float:
        return 0.5 * self._extent / (self.resolutions[-1] - 1)

    def grid_features(self, x, band_weights=None):
        lo, hi = self.aabb[:3], self.aabb[3:]
        u = (2.0 * (x - lo) / (hi - lo) - 1.0).to(self.grids[0].dtype)  # [N,3] in [-1,1]
        f = encode(u, list(self.grids), self.grid_kernel, self.resolutions)  # [N, L*C]
        if band_weights is None:
            return f
        L, n = len(self.grids), x.shape[0]
        bw = band_weights.to(f.dtype)
        return (f.view(n, L, -1) * (bw[None, :, None] if bw.dim() == 1 else bw[:, :, None])).view(n, -1)

    def _sdf_feat(self, x, band_weights=None):
        gf = self.grid_features(x, band_weights)
        h = torch.cat([gf, x], -1)
        for li, lin in enumerate(self.sdf_layers):
            h = lin(h)
            if li < len(self.sdf_layers) - 1:
                h = F.relu(h)
        sdf = x.norm(dim=-1) - self.p.init_radius + h[:, 0]
        # the colour decoder also reads the raw grid features (appearance detail)
        return sdf, torch.cat([h[:, 1:], gf], -1)

    def _color(self, x, dirs, feat, normals):
        h = [feat, fourier_encode(dirs, self.p.dir_bands)]
        if self.color_uses_ray_normal:
            h.append(-(normals * dirs).sum(-1, keepdim=True))  # [N,1]: 1 facing the camera
        h = torch.cat(h, -1)
        for li, lin in enumerate(self.color_layers):
            h = lin(h)
            if li < len(self.color_layers) - 1:
                h = F.relu(h)
        return torch.sigmoid(h)

    def grid_parameters(self):
        return list(self.grids.parameters())


def _read_extent_after_load(module: GridField, incompatible_keys) -> None:
    module._read_extent()  # a module-level function: a field with its hook still pickles


def make_field(p: FieldParams) -> FieldBase:
    """Build the field variant named by ``p.kind``."""
    if p.kind == "mlp":
        return MLPField(p)
    if p.kind == "grid":
        return GridField(p)
    raise ValueError(f"unknown field kind {p.kind!r}")
