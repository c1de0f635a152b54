"""Fingerprints: a stage's version is named by a hash of the parameters it declares, the code it can
import (the stage module and every ``manifoldneus``/``stages`` module it reaches, and the C++ they
compile), its input files, and the content of its upstream versions; and the content digests of
a version's files (what downstream fingerprints use)."""
from __future__ import annotations

import ast
import functools
import hashlib
import json
import os
import types
from pathlib import Path
from typing import TYPE_CHECKING

from runner import common
from runner.common import LOG, MANIFEST
from runner.params import stage_params
from runner.registry import Stage

if TYPE_CHECKING:
    from runner.store import Store


OWN_PACKAGES = ("manifoldneus", "stages")


def _module_file(name: str) -> Path | None:
    """The source file of one of our own modules (``a.b`` -> ``a/b.py`` or ``a/b/__init__.py``), else None."""
    if name.split(".")[0] not in OWN_PACKAGES:
        return None
    base = common.ROOT.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _syntax_tree(path: Path) -> ast.Module:
    """The file's syntax tree, parsed once per content: every run and status hashes the code of all
    stages, and parsing the same ~40 files for each of them took 2-3 s a call."""
    stat = path.stat()
    return _parse(path, stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=512)
def _parse(path: Path, mtime_ns: int, size: int) -> ast.Module:
    return ast.parse(path.read_bytes(), filename=str(path))


def _imported_names(path: Path, module_name: str) -> frozenset[str]:
    """Every module name an import statement in the file may refer to, wherever the statement is
    (module level or inside a function body): read from the syntax tree, not from what is loaded."""
    stat = path.stat()
    return _imported_names_of(path, module_name, stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=512)
def _imported_names_of(path: Path, module_name: str, mtime_ns: int, size: int) -> frozenset[str]:
    is_package = path.name == "__init__.py"
    package = module_name if is_package else module_name.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(_syntax_tree(path)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            names.add(source)
            # `from pkg import mod` names a module; `from mod import func` does not (no such file).
            names.update(f"{source}.{alias.name}" for alias in node.names)
    return frozenset(names)


def _native_sources(path: Path) -> list[Path]:
    """Files a module compiles at run time, named by its literal ``__native_sources__`` (paths
    relative to the module's folder)."""
    for node in _syntax_tree(path).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__native_sources__" for t in node.targets):
            return [path.parent / rel for rel in ast.literal_eval(node.value)]
    return []


def _code_files(module: types.ModuleType) -> list[Path]:
    """Source files of the stage module and of every ``manifoldneus``/``stages`` module it can reach
    through imports, transitively, including imports inside function bodies (an AST pass, so a
    lazily imported module is covered before it has ever been loaded), and the C++ they compile."""
    seen: dict[str, Path] = {}
    todo = [module.__name__]
    while todo:
        name = todo.pop()
        path = _module_file(name)
        if name in seen or path is None:
            continue
        seen[name] = path
        # A submodule also runs its packages' __init__; `stages/__init__.py` is the DAG's registry
        # (its shape is in the upstream fingerprints, its shared sections are hashed by value).
        todo.extend(p for p in (".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1))
                    if p != "stages")
        todo.extend(_imported_names(path, name))
    native = [src for path in seen.values() for src in _native_sources(path)]
    return sorted(set(seen.values()) | set(native))


def code_hash(stage: Stage) -> str:
    h = hashlib.sha256()
    for path in _code_files(stage.module):
        h.update(path.relative_to(common.ROOT).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def own_ingredients(stages: dict[str, Stage], resolved: dict, scene) -> dict[str, dict]:
    """Per stage, what its fingerprint hashes besides its upstream: params, code, input files."""
    out = {}
    for name, stage in stages.items():
        out[name] = {"params": stage_params(stage, resolved), "code": code_hash(stage)}
        if hasattr(stage.module, "input_signature"):
            out[name]["inputs"] = stage.module.input_signature(scene, resolved[stage.sections[0]])
    return out


def chain_fingerprints(stages: dict[str, Stage], own: dict[str, dict], store: Store | None = None) -> dict[str, dict]:
    """Per stage: fingerprint and the ingredients that made it (for status and params-diff).

    An upstream enters by the content digest of its version when that version exists in ``store``
    (so equal bytes give equal downstream fingerprints), else by its fingerprint; where the stage
    declares the files it reads of it (``READS``), by the digest of those files only."""
    out: dict[str, dict] = {}
    for name, stage in stages.items():
        upstream = {u: out[u]["fingerprint"] for u in stage.upstream}
        content = {u: (store.content(u, fp, stage.reads.get(u)) if store is not None else None) or f"recipe:{fp}"
                   for u, fp in upstream.items()}
        ingredients = {**own[name], "upstream_content": content}
        blob = json.dumps(ingredients, sort_keys=True, default=str).encode()
        out[name] = {**ingredients, "upstream": upstream, "fingerprint": hashlib.sha256(blob).hexdigest()[:12]}
    return out


def compute_fingerprints(stages: dict[str, Stage], resolved: dict, scene, store: Store | None = None) -> dict[str, dict]:
    return chain_fingerprints(stages, own_ingredients(stages, resolved, scene), store)


def file_digests(folder: Path) -> dict[str, dict]:
    """Size and SHA-256 of every file under ``folder`` (symlinks by their target), the manifest
    and the log excluded: {relative path: {"size", "sha256"} | {"link"}}."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        here = Path(dirpath)
        for name in sorted(filenames + [d for d in dirnames if (here / d).is_symlink()]):
            path = here / name
            rel = path.relative_to(folder).as_posix()
            if rel in (MANIFEST, LOG):
                continue
            if path.is_symlink():
                out[rel] = {"link": os.readlink(path)}
                continue
            out[rel] = {"size": path.stat().st_size, "sha256": sha256_of(path)}
    return out


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def content_digest(files: dict[str, dict]) -> str:
    blob = json.dumps({k: v.get("sha256", v.get("link")) for k, v in files.items()}, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
