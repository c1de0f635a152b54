"""Typed, validated parameters.

Each stage module defines ``Params``, a dataclass whose fields are declared with
:func:`param` (default, one-line help, optional range or choices). ``params.yaml`` holds
one section per dataclass; profiles (``fast``, ``paper``) override keys per section.
Resolution order: dataclass defaults < params.yaml section < profile < ``--set``.
Unknown keys, wrong types and out-of-range values raise :class:`ParamError` naming the key.
"""
from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import MISSING, field, fields
from typing import Any


class ParamError(ValueError):
    """A parameter that is unknown, of the wrong type or out of range."""


def param(default, help: str, *, lo=None, hi=None, choices=None, check=None):
    """A dataclass field with documentation and validation metadata. ``check(value)`` returns what is
    wrong with a value (a sentence), or None."""
    meta = {"help": help, "lo": lo, "hi": hi, "choices": choices, "check": check}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


def _coerce(key: str, value: Any, typ) -> Any:
    origin = typing.get_origin(typ)
    args = typing.get_args(typ)
    if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(key, value, a)
            except ParamError as e:
                errors.append(str(e))
        raise ParamError(errors[0] if errors else f"{key}: bad value {value!r}")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ParamError(f"{key}: expected a list, got {value!r}")
        inner = args[0] if args else Any
        return [_coerce(key, v, inner) for v in value]
    if typ is Any:
        return value
    if typ is bool:
        if isinstance(value, bool):
            return value
        raise ParamError(f"{key}: expected true/false, got {value!r}")
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ParamError(f"{key}: expected an integer, got {value!r}")
        return value
    if typ is float:
        if isinstance(value, str):  # YAML 1.1 reads 5e-4 (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(value):  # NaN passes every range check and poisons what it reaches
            raise ParamError(f"{key}: expected a finite number, got {value!r}")
        return float(value)
    if typ is str:
        if isinstance(value, bool):  # YAML 1.1 reads on/off (and yes/no) as booleans: `crop_to_object: off`
            value = "on" if value else "off"
        if not isinstance(value, str):
            raise ParamError(f"{key}: expected a string, got {value!r}")
        return value
    if origin is dict or typ is dict:
        if not isinstance(value, dict):
            raise ParamError(f"{key}: expected a mapping, got {value!r}")
        return dict(value)
    return value


def build(cls, section: str, values: dict | None):
    """Instantiate ``cls`` from a mapping, validating every key and value."""
    values = dict(values or {})
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ParamError(
            f"unknown parameter {section}.{unknown[0]} (known keys of '{section}': {', '.join(sorted(known))})"
        )
    kwargs = {}
    for name, f in known.items():
        key = f"{section}.{name}"
        if name in values:
            v = _coerce(key, values[name], hints[name])
        elif f.default is not MISSING:
            v = f.default
        else:
            v = f.default_factory()  # type: ignore[misc]
        m = f.metadata
        if m.get("choices") is not None and v not in m["choices"]:
            raise ParamError(f"{key}: {v!r} is not one of {m['choices']}")
        for item in v if isinstance(v, list) else [v]:
            if isinstance(item, (int, float)) and not isinstance(item, bool):
                if m.get("lo") is not None and item < m["lo"]:
                    raise ParamError(f"{key}: {item} is below the minimum {m['lo']}")
                if m.get("hi") is not None and item > m["hi"]:
                    raise ParamError(f"{key}: {item} is above the maximum {m['hi']}")
        problem = m["check"](v) if m.get("check") else None
        if problem:
            raise ParamError(f"{key}: {problem}")
        kwargs[name] = v
    return cls(**kwargs)


def as_dict(obj) -> dict:
    return dataclasses.asdict(obj)


def describe(cls) -> list[tuple[str, Any, str]]:
    """(name, default, help) per field, for documentation and ``show``."""
    out = []
    for f in fields(cls):
        d = f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]
        out.append((f.name, d, f.metadata.get("help", "")))
    return out


def parse_override(text: str) -> tuple[str, str, Any]:
    """``section.key=value`` -> (section, key, YAML-parsed value)."""
    import yaml

    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ParamError(f"bad --set {text!r}: expected section.key=value, e.g. schedule.alpha=0.5")
    lhs, rhs = text.split("=", 1)
    section, key = lhs.strip().split(".", 1)
    try:
        value = yaml.safe_load(rhs) if rhs.strip() else ""
    except yaml.YAMLError as e:
        raise ParamError(f"bad --set {text!r}: value is not valid YAML ({e})") from None
    return section, key, value


def device_problem(device: str) -> str | None:
    """What keeps torch from computing on ``device`` on this machine, or None. Checked when a run
    starts (on the machine that runs it), not when parameters are read (a login node submitting to
    GPU nodes has none)."""
    import torch

    try:
        d = torch.device(device)
    except RuntimeError:
        return f"{device!r} is not a torch device (cpu, cuda or cuda:N)"
    if d.type == "cpu":
        return None
    if d.type != "cuda":
        return f"{device!r}: only cpu and cuda are supported"
    if not torch.cuda.is_available():
        return f"{device!r} is not available on this machine (torch {torch.__version__} sees no CUDA device); use cpu"
    if d.index is not None and d.index >= torch.cuda.device_count():
        return f"{device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)"
    return None


@dataclasses.dataclass
class RunParams:
    """Section `run` of params.yaml: settings shared by the stages that declare it."""

    device: str = param("cpu", "torch device for the neural stages: cpu, cuda or cuda:N", choices=None)
    seed: int = param(0, "Random seed of every stochastic step", lo=0)
    threads: int = param(2, "CPU threads for torch and thread pools", lo=1)


@dataclasses.dataclass
class SplitParams:
    """Section `split` of params.yaml: which views are held out for novel-view evaluation. Views are
    held out only where cameras to score them come with the input (every layout but a plain folder
    of photos): in a user's own capture every photo gets a pose."""

    holdout_every: int = param(8, "Hold out views 0, k, 2k, ... from scheduling and training (0 = none); in inputs "
                               "that come with cameras only, unless holdout_without_cameras", lo=0)
    holdout_without_cameras: bool = param(False, "Hold views out of a plain folder of photos too (nothing can score "
                                           "them there: they get no pose and are not exported)")


def holdout_mask(n_views: int, split: SplitParams, has_cameras: bool = True):
    """bool [N]: True for held-out views; ``has_cameras``: the input comes with cameras to score them."""
    import numpy as np

    mask = np.zeros(n_views, bool)
    if split.holdout_every > 0 and (has_cameras or split.holdout_without_cameras):
        mask[:: split.holdout_every] = True
    return mask
