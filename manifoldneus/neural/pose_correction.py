"""Learnable per-view pose corrections: the one place that owns them (as nerfstudio's
``CameraOptimizer``; the Lie algebra is :mod:`manifoldneus.geometry.cameras`').

A correction is an se(3) vector per view, ``xi`` [N,6], applied on the left of the initial
world-to-camera pose: ``w2c = exp(xi) @ w2c_init`` (:func:`cameras.apply_correction`). This module
owns which views learn, the step from which they do (exactly that step: before it every
correction is held at zero), their AdamW optimiser and its learning rate, and the check that a
learned pose jumped. The :class:`~manifoldneus.neural.train.Trainer` composes it.
"""
from __future__ import annotations

import numpy as np
import torch

from manifoldneus.geometry.cameras import apply_correction, rotation_angle_deg


class PoseCorrections:
    """Corrections of ``w2c_init`` [N,3,4]; ``trainable`` are the view indices that learn (None or
    empty: none learn and :meth:`poses` is ``w2c_init``), from step ``start`` on. ``translation``
    False learns rotations only: a correction on the left with no translation part keeps every
    camera centre where ``w2c_init`` puts it."""

    def __init__(self, w2c_init: torch.Tensor, trainable=None, *, start: int = 0, lr: float = 0.0,
                 weight_decay: float = 0.0, translation: bool = True):
        n = w2c_init.shape[0]
        dev = w2c_init.device
        self.w2c_init = w2c_init  # [N,3,4]
        self.start = int(start)
        self.xi = torch.nn.Parameter(torch.zeros(n, 6, device=dev))  # [N,6] (rho, omega)
        self.mask = torch.zeros(n, 6, device=dev)  # [N,6] 1 = this component of this view learns
        if trainable is not None and len(trainable):
            self.mask[torch.as_tensor(np.asarray(trainable, int), dtype=torch.long, device=dev)] = 1.0
        if not translation:
            self.mask[:, :3] = 0.0  # rho: zero gradient, so AdamW (no decay on zeros) keeps it at zero
        self._learning = bool(self.mask.any())  # read once: asked every step, a host read on a GPU
        self.opt = None
        if self.learning:
            self.opt = torch.optim.AdamW([{"params": [self.xi], "lr": lr, "base_lr": lr}], weight_decay=weight_decay)

    @property
    def learning(self) -> bool:
        return self._learning

    def active(self, step: int) -> bool:
        """Whether the corrections move at ``step`` (learning, and not frozen any more)."""
        return self.learning and step >= self.start

    def poses(self, step: int) -> torch.Tensor:
        """World-to-camera poses [N,3,4] at ``step``."""
        if not self.learning:
            return self.w2c_init
        mask = self.mask if step >= self.start else torch.zeros_like(self.mask)
        return apply_correction(self.xi * mask, self.w2c_init)

    def set_lr(self, factor: float) -> None:
        if self.opt is not None:
            for g in self.opt.param_groups:
                g["lr"] = g["base_lr"] * factor

    def zero_grad(self) -> None:
        if self.opt is not None:
            self.opt.zero_grad(set_to_none=True)

    def step(self) -> None:
        if self.opt is not None:
            self.opt.step()

    def reset(self) -> None:
        """Every correction back to zero (the poses the round started from)."""
        with torch.no_grad():
            self.xi.zero_()

    def grad_norms(self) -> np.ndarray:
        """|d loss / d xi| per view [N] of the last backward pass (zeros before any)."""
        g = self.xi.grad
        return np.zeros(self.xi.shape[0]) if g is None else g.detach().norm(dim=-1).cpu().numpy()

    def state_dict(self) -> dict:
        return {"xi": self.xi.detach().clone(), "opt": None if self.opt is None else self.opt.state_dict()}

    def load_state_dict(self, s: dict) -> None:
        with torch.no_grad():
            self.xi.copy_(s["xi"])
        if self.opt is not None and s.get("opt") is not None:
            self.opt.load_state_dict(s["opt"])

    def jump(self, xi_before: torch.Tensor, step: int, max_turn_deg: float, names) -> str | None:
        """Why the corrections count as diverged since ``xi_before`` (non-finite, or a view turned by
        more than ``max_turn_deg``; 0 = no turn check), or None."""
        if not self.learning:
            return None
        with torch.no_grad():
            if not bool(torch.isfinite(self.xi).all()):
                return "non-finite pose correction"
            if max_turn_deg <= 0:
                return None
            now = self.poses(step)[:, :3, :3]  # [N,3,3]
            before = apply_correction(xi_before * self.mask, self.w2c_init)[:, :3, :3]  # [N,3,3]
            turn = rotation_angle_deg((now @ before.transpose(-1, -2)).double().cpu().numpy())  # [N]
        worst = int(turn.argmax())
        if turn[worst] > max_turn_deg:
            name = names[worst] if worst < len(names) else str(worst)
            return f"pose of view {name} turned {turn[worst]:.1f} deg"
        return None
