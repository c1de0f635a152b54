"""The stages and their DAG: each stage module's declarations (UPSTREAM, SECTIONS, OUTPUTS, Params and,
optionally, READS and UPSTREAM_IF),
read from ``stages.STAGES``, and which of them a run brings up to date."""
from __future__ import annotations

import dataclasses
import importlib
import types
from dataclasses import dataclass, field

from runner.common import PipelineError


@dataclass
class Stage:
    name: str
    module: types.ModuleType
    upstream: tuple[str, ...]
    sections: tuple[str, ...]
    outputs: tuple[str, ...]
    reads: dict[str, tuple[str, ...]] = field(default_factory=dict)  # upstream -> the files of its version run() reads (READS); else all of them
    # upstream -> (key of the stage's own section, value): read only when that key has that value (UPSTREAM_IF)
    upstream_if: dict[str, tuple[str, object]] = field(default_factory=dict)

    @property
    def params_cls(self):
        return self.module.Params

    def keys_read(self) -> dict[str, frozenset | None]:
        """Section -> the keys the stage declares it reads (``"section.key"`` in SECTIONS), or None
        for a whole section (``"section"``). Only what is declared enters its fingerprint."""
        out: dict[str, set | None] = {}
        for entry in self.sections:
            section, _, key = entry.partition(".")
            if not key or out.get(section, set()) is None:
                out[section] = None
            else:
                out.setdefault(section, set()).add(key)
        return {k: None if v is None else frozenset(v) for k, v in out.items()}


def load_stages() -> dict[str, Stage]:
    """Import every stage listed in ``stages.STAGES`` and check the DAG's rules."""
    import stages as registry

    out: dict[str, Stage] = {}
    for name in registry.STAGES:
        module = importlib.import_module(f"stages.{name}")
        reads = {u: tuple(files) for u, files in getattr(module, "READS", {}).items()}
        stage = Stage(name, module, tuple(module.UPSTREAM), tuple(module.SECTIONS), tuple(module.OUTPUTS), reads,
                      dict(getattr(module, "UPSTREAM_IF", {})))
        if set(stage.upstream_if) - set(stage.upstream):
            raise PipelineError(f"stage {name}: UPSTREAM_IF names {sorted(set(stage.upstream_if) - set(stage.upstream))}, "
                                "not upstream")
        if set(reads) - set(stage.upstream):
            raise PipelineError(f"stage {name}: READS names {sorted(set(reads) - set(stage.upstream))}, not upstream")
        for up in stage.upstream:
            if up not in out:
                raise PipelineError(f"stage {name}: upstream {up!r} is not an earlier stage in stages.STAGES")
        if "ground_truth" in stage.upstream and name not in registry.GROUND_TRUTH_READERS:
            raise PipelineError(
                f"stage {name} may not read ground truth: only {sorted(registry.GROUND_TRUTH_READERS)} can"
            )
        out[name] = stage
    return out


def for_params(stages: dict[str, Stage], resolved: dict) -> dict[str, Stage]:
    """The stages as a run with the ``resolved`` parameters has them: a conditional upstream
    (``UPSTREAM_IF``) only where the stage's own parameter asks for it, so that neither its version
    nor its parameters enter the stage's fingerprint otherwise, and a run does not compute it for it."""
    out = {}
    for name, s in stages.items():
        drop = {u for u, (key, value) in s.upstream_if.items() if getattr(resolved[s.sections[0]], key) != value}
        out[name] = dataclasses.replace(s, upstream=tuple(u for u in s.upstream if u not in drop)) if drop else s
    return out


def section_classes(stages: dict[str, Stage]) -> dict[str, type]:
    import stages as registry

    classes = dict(registry.SHARED_SECTIONS)
    for s in stages.values():
        classes[s.sections[0]] = s.params_cls
    return classes


def upstream_closure(stages: dict[str, Stage], name: str) -> set[str]:
    """`name` and every stage it depends on, directly or through others."""
    out, todo = set(), [name]
    while todo:
        current = todo.pop()
        if current not in out:
            out.add(current)
            todo.extend(stages[current].upstream)
    return out


def select(stages: dict[str, Stage], until: str | list[str] | None, only: str | list[str] | None) -> list[str]:
    """The stages a run brings up to date, in DAG order: all; `until` (one stage or several) and what
    it depends on (not the stages listed before it that it does not need); or `only` (one stage, or
    several whose upstream are among them or computed)."""
    names = list(stages)
    only_list = [only] if isinstance(only, str) else list(only or [])
    until_list = [until] if isinstance(until, str) else list(until or [])
    for flag, value in (*(("--until", u) for u in until_list), *(("--only", o) for o in only_list)):
        if value not in stages:
            raise PipelineError(f"unknown stage {value!r} for {flag} (stages: {', '.join(names)})")
    if only_list:
        return [n for n in names if n in only_list]
    if until_list:
        needed = set().union(*(upstream_closure(stages, u) for u in until_list))
        return [n for n in names if n in needed]
    return names
