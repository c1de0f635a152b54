"""Parameters: params.yaml, its profiles and presets, and ``--set`` overrides, resolved into each
section's typed dataclass; and what of them one stage declares it reads."""
from __future__ import annotations

from pathlib import Path

import yaml

from manifoldneus import config
from manifoldneus.config import ParamError
from runner.common import DEFAULT_PARAMS, PipelineError
from runner.registry import Stage, section_classes


def _expect_mapping(value, where: str) -> None:
    if value is not None and not isinstance(value, dict):
        raise ParamError(f"{where}: expected a mapping of key: value, got {type(value).__name__} {value!r}")


def read_params_file(path: Path) -> dict:
    """params.yaml as a mapping; a missing, empty, malformed or wrongly shaped file is a
    ParamError that names the file (and the line, for YAML syntax)."""
    if not path.is_file():
        raise ParamError(f"parameter file {path} not found (the project's own is {DEFAULT_PARAMS})")
    text = path.read_text()
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}, line {mark.line + 1}" if mark is not None else str(path)
        near = text.splitlines()[max(mark.line - 1, 0):mark.line + 1] if mark is not None else text.splitlines()
        tabs = "; indent with spaces, not tabs" if any("\t" in line for line in near) else ""
        raise ParamError(f"{where}: not valid YAML ({getattr(e, 'problem', None) or e}){tabs}") from None
    if raw is None:
        raise ParamError(f"{path} is empty: it needs at least the `profiles` section (see {DEFAULT_PARAMS})")
    _expect_mapping(raw, f"{path}: the top level")
    return dict(raw)


def resolve_params(
    stages: dict[str, Stage],
    params_path: Path = DEFAULT_PARAMS,
    overrides: list[str] = (),
    profile: str | None = None,
    preset: str | None = None,
) -> dict[str, object]:
    """Resolved, validated parameters: section name -> dataclass instance.

    Order: dataclass defaults < params.yaml < profile < preset < ``--set`` overrides.
    """
    raw = read_params_file(Path(params_path))
    classes = section_classes(stages)
    profiles = raw.pop("profiles", {}) or {}
    presets = raw.pop("presets", {}) or {}
    profile = profile or raw.pop("profile", "fast")
    raw.pop("profile", None)
    for section, values in raw.items():
        if section not in classes:
            raise ParamError(f"{params_path}: unknown section {section!r} (known: {', '.join(sorted(classes))})")
        _expect_mapping(values, f"{params_path}: section {section!r}")
    if not profiles:
        raise ParamError(f"{params_path} defines no `profiles` (the project's {DEFAULT_PARAMS} has fast and paper)")
    if profile not in profiles:
        raise ParamError(f"unknown profile {profile!r} ({params_path} defines: {', '.join(sorted(profiles))})")
    if preset is not None and preset not in presets:
        raise ParamError(f"unknown preset {preset!r} (params.yaml defines: {', '.join(sorted(presets))})")
    merged = {s: dict(raw.get(s) or {}) for s in classes}
    for layer_name, layer in (("profile " + profile, profiles[profile]), ("preset " + str(preset), presets.get(preset))):
        _expect_mapping(layer, f"{params_path}: {layer_name}")
        for section, values in (layer or {}).items():
            if section not in classes:
                raise ParamError(f"{layer_name}: unknown section {section!r}")
            _expect_mapping(values, f"{params_path}: {layer_name}, section {section!r}")
            merged[section].update(values or {})
    for text in overrides:
        section, key, value = config.parse_override(text)
        if section not in classes:
            raise ParamError(f"bad --set {text!r}: unknown section {section!r} (known: {', '.join(sorted(classes))})")
        merged[section][key] = value
    resolved = {s: config.build(cls, s, merged[s]) for s, cls in classes.items()}
    resolved["_profile"] = profile  # recorded in manifests; not a section
    resolved["_preset"] = preset
    return resolved


def stage_params(stage: Stage, resolved: dict) -> dict:
    """The parameters a stage declares (whole sections, or the declared keys of a section)."""
    out = {}
    for section, keys in stage.keys_read().items():
        values = config.as_dict(resolved[section])
        unknown = sorted(set(keys or ()) - set(values))
        if unknown:
            raise PipelineError(f"stage {stage.name} declares {[f'{section}.{k}' for k in unknown]}: no such key")
        out[section] = values if keys is None else {k: values[k] for k in sorted(keys)}
    return out


class DeclaredKeys:
    """A section seen through the keys a stage declared: any other key is an error, so a stage cannot
    read a parameter its fingerprint does not cover."""

    def __init__(self, stage: str, section: str, values, keys: frozenset):
        self._stage, self._section, self._values, self._keys = stage, section, values, keys

    def __getattr__(self, key: str):
        if key.startswith("_"):
            raise AttributeError(key)
        if key not in self._keys:
            raise PipelineError(f"stage {self._stage} reads {self._section}.{key} without declaring it in SECTIONS "
                                f"(it declares {sorted(f'{self._section}.{k}' for k in self._keys)})")
        return getattr(self._values, key)
