#!/usr/bin/env python
"""manifoldneus pipeline: a cached DAG of stages, each writing a versioned artifact.

    python pipeline.py run --scene S [--until STAGE | --only STAGE] [--set sec.key=value ...]
                           [--force STAGE] [--profile fast|paper] [--preset NAME]
    python pipeline.py status --scene S
    python pipeline.py show --scene S STAGE
    python pipeline.py params-diff --scene S STAGE
    python pipeline.py verify --scene S
    python pipeline.py view --scene S [--preset NAME] [--out FILE] [--open] [--screenshot PNG]
    python pipeline.py gc [--scene S] [--dry-run]

Artifact layout: ``artifacts/<scene>/<stage>/<fingerprint>/`` (files + ``manifest.json`` +
``log.txt``) and ``artifacts/<scene>/<stage>/current`` (symlink to the version in use).
A fingerprint hashes the stage's resolved parameter sections, the source of the stage module
and of every ``manifoldneus``/``stages`` module it can import (module level or inside a function),
and the content of its upstream stages' outputs (plus, for ``ingest``, a signature of the input
files). Versions are written to a temporary folder and renamed when complete, so an interrupted
run never leaves a version that looks done.

Each manifest records the size and SHA-256 of every output file and one content digest over them.
Downstream fingerprints use that digest, not the upstream's fingerprint (DVC's run-cache idea): an
upstream recomputed to the same bytes (a comment-only code change) leaves its downstream fresh.
``status`` and ``run`` check presence and sizes of every file they trust (cheap); ``verify``
re-hashes them. A damaged version is never read: the run stops and names the file and the command
that rebuilds it.
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import errno
import fcntl
import hashlib
import importlib
import importlib.metadata
import json
import logging
import os
import re
import shlex
import shutil
import signal
import socket
import sys
import threading
import time
import types
from dataclasses import dataclass
from pathlib import Path

# Small dense solves (BA, Umeyama, eigh) are slower with threaded OpenBLAS on a loaded 2-core
# machine than on one thread; torch keeps its own thread pool (run.threads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Busy-waiting OpenMP threads made training steps up to 8x slower when the cores are shared.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import cv2  # noqa: E402,F401  - loads the system zlib before pycolmap's own deflate symbols can shadow it
import pycolmap  # noqa: E402,F401  - imported before main() takes SIGTERM from the failure handler pycolmap installs
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from manifoldneus import __version__, config, executor  # noqa: E402
from manifoldneus.config import ParamError  # noqa: E402
from manifoldneus.scenes import SceneError, resolve_scene  # noqa: E402

DEFAULT_ARTIFACTS = ROOT / "artifacts"
DEFAULT_PARAMS = ROOT / "params.yaml"
MANIFEST = "manifest.json"
LOG = "log.txt"
LIBRARIES = ("numpy", "scipy", "torch", "cv2", "pycolmap", "skimage", "trimesh", "zarr", "roma")


class PipelineError(RuntimeError):
    """A user-facing error: printed as one clear message, without a traceback."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (what `timeout`, SLURM and `kill` send): handled as Ctrl-C is, so the stage in progress
    is moved aside as `.failed-*` and nothing half-written is published."""


def _raise_terminated(signum, frame):
    raise Terminated()


# ---------------------------------------------------------------------------- stages


@dataclass
class Stage:
    name: str
    module: types.ModuleType
    upstream: tuple[str, ...]
    sections: tuple[str, ...]
    outputs: tuple[str, ...]

    @property
    def params_cls(self):
        return self.module.Params

    def reads(self) -> dict[str, frozenset | None]:
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
        stage = Stage(name, module, tuple(module.UPSTREAM), tuple(module.SECTIONS), tuple(module.OUTPUTS))
        for up in stage.upstream:
            if up not in out:
                raise PipelineError(f"stage {name}: upstream {up!r} is not an earlier stage in stages.STAGES")
        if "ground_truth" in stage.upstream and name not in registry.GROUND_TRUTH_READERS:
            raise PipelineError(
                f"stage {name} may not read ground truth: only {sorted(registry.GROUND_TRUTH_READERS)} can"
            )
        out[name] = stage
    return out


def section_classes(stages: dict[str, Stage]) -> dict[str, type]:
    import stages as registry

    classes = dict(registry.SHARED_SECTIONS)
    for s in stages.values():
        classes[s.sections[0]] = s.params_cls
    return classes


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


# ---------------------------------------------------------------------------- fingerprints


OWN_PACKAGES = ("manifoldneus", "stages")


def _module_file(name: str) -> Path | None:
    """The source file of one of our own modules (``a.b`` -> ``a/b.py`` or ``a/b/__init__.py``), else None."""
    if name.split(".")[0] not in OWN_PACKAGES:
        return None
    base = ROOT.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _imported_names(path: Path, module_name: str) -> set[str]:
    """Every module name an import statement in the file may refer to, wherever the statement is
    (module level or inside a function body): read from the syntax tree, not from what is loaded."""
    is_package = path.name == "__init__.py"
    package = module_name if is_package else module_name.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
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
    return names


def _native_sources(path: Path) -> list[Path]:
    """Files a module compiles at run time, named by its literal ``__native_sources__`` (paths
    relative to the module's folder)."""
    for node in ast.parse(path.read_text(), filename=str(path)).body:
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
        h.update(path.relative_to(ROOT).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def stage_params(stage: Stage, resolved: dict) -> dict:
    """The parameters a stage declares (whole sections, or the declared keys of a section)."""
    out = {}
    for section, keys in stage.reads().items():
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
    (so equal bytes give equal downstream fingerprints), else by its fingerprint."""
    out: dict[str, dict] = {}
    for name, stage in stages.items():
        upstream = {u: out[u]["fingerprint"] for u in stage.upstream}
        content = {u: (store.content(u, fp) if store is not None else None) or f"recipe:{fp}" for u, fp in upstream.items()}
        ingredients = {**own[name], "upstream_content": content}
        blob = json.dumps(ingredients, sort_keys=True, default=str).encode()
        out[name] = {**ingredients, "upstream": upstream, "fingerprint": hashlib.sha256(blob).hexdigest()[:12]}
    return out


def compute_fingerprints(stages: dict[str, Stage], resolved: dict, scene, store: Store | None = None) -> dict[str, dict]:
    return chain_fingerprints(stages, own_ingredients(stages, resolved, scene), store)


# ---------------------------------------------------------------------------- output content


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


# ---------------------------------------------------------------------------- store


class Store:
    """Versioned artifacts of one scene."""

    def __init__(self, root: Path, scene_name: str, preset: str | None = None):
        self.scene_dir = Path(root) / scene_name
        # Versions are shared by fingerprint; each preset keeps its own pointers, so that a
        # baseline (e.g. neus-barf) never moves the default run's `current`.
        self.pointer = "current" if preset is None else f"current@{preset}"

    def stage_dir(self, stage: str) -> Path:
        return self.scene_dir / stage

    def version_dir(self, stage: str, fingerprint: str) -> Path:
        return self.stage_dir(stage) / fingerprint

    def is_complete(self, stage: str, fingerprint: str) -> bool:
        """A version exists once its manifest is written; an unreadable manifest (truncated by a
        crash or an edit) makes it missing, so it is recomputed rather than trusted."""
        try:
            json.loads((self.version_dir(stage, fingerprint) / MANIFEST).read_text())
        except (OSError, ValueError):
            return False
        return True

    def current(self, stage: str) -> str | None:
        link = self.stage_dir(stage) / self.pointer
        if not link.is_symlink():
            return None
        fp = os.readlink(link)
        return fp if self.is_complete(stage, fp) else None

    def set_current(self, stage: str, fingerprint: str) -> None:
        tmp = self.stage_dir(stage) / f".current-{_process()}"
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(fingerprint, tmp)
        os.replace(tmp, self.stage_dir(stage) / self.pointer)

    def content(self, stage: str, fingerprint: str) -> str | None:
        """The content digest of a complete version (None: absent, unreadable, or written before digests)."""
        try:
            return json.loads((self.version_dir(stage, fingerprint) / MANIFEST).read_text()).get("content")
        except (OSError, ValueError):
            return None

    def damage(self, stage: str, fingerprint: str, deep: bool = False) -> list[str]:
        """What is wrong with a version's files against its manifest: missing files and wrong sizes
        (cheap), and with ``deep`` also content that no longer matches its hash. [] = intact."""
        folder = self.version_dir(stage, fingerprint)
        problems = []
        for rel, rec in self.manifest(stage, fingerprint).get("files", {}).items():
            path = folder / rel
            if "link" in rec:
                if not path.is_symlink() or os.readlink(path) != rec["link"]:
                    problems.append(f"{path}: the link to {rec['link']} is gone")
            elif not path.is_file():
                problems.append(f"{path}: missing")
            elif path.stat().st_size != rec["size"]:
                problems.append(f"{path}: {path.stat().st_size} bytes, {rec['size']} when written")
            elif deep and sha256_of(path) != rec["sha256"]:
                problems.append(f"{path}: content differs from its hash when written")
        return problems

    def manifest(self, stage: str, fingerprint: str | None = None) -> dict | None:
        fingerprint = fingerprint or self.current(stage)
        if fingerprint is None:
            return None
        return json.loads((self.version_dir(stage, fingerprint) / MANIFEST).read_text())

    def lineage(self, stage: str) -> dict[str, Path]:
        """The current version of ``stage`` and the versions of all its upstream stages that it was
        computed from (as its manifests name them): one consistent set, whatever the other stages'
        pointers say now. Stage -> version folder; {} when ``stage`` has no current version."""
        fp = self.current(stage)
        todo, out = ([(stage, fp)] if fp else []), {}
        while todo:
            name, fp = todo.pop()
            if name in out:
                continue
            out[name] = self.version_dir(name, fp)
            todo.extend(self.manifest(name, fp).get("upstream", {}).items())
        return out

    # A run's record: the versions it has started or finished, written as it goes. A run that does
    # not end normally (a failure, Ctrl-C, SIGKILL, a lost node) leaves it, so that gc keeps what
    # running the same command again resumes from (its finished versions and its checkpoints).
    def record_run(self, versions: dict[str, str]) -> None:
        path = self.scene_dir / ".runs" / f"{_process()}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps({"pointer": self.pointer, "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
                                   "versions": versions}))
        os.replace(tmp, path)

    def end_run(self) -> None:
        """A run ended normally: drop its record and those that interrupted runs of the same pointer
        left (this one has done what they would resume)."""
        (self.scene_dir / ".runs" / f"{_process()}.json").unlink(missing_ok=True)
        for path, record in self.interrupted_runs():
            if record.get("pointer") == self.pointer:
                path.unlink(missing_ok=True)

    def interrupted_runs(self) -> list[tuple[Path, dict]]:
        """(path, record) of the runs that ended without removing their record (interrupted)."""
        out = []
        for path in sorted((self.scene_dir / ".runs").glob("*.json")):
            host, _, pid = path.stem.rpartition("-")
            if _process_alive(host, pid):
                continue
            try:
                out.append((path, json.loads(path.read_text())))
            except (OSError, ValueError):
                path.unlink(missing_ok=True)  # half-written: its run was killed while writing it
        return out

    # Locks are flock(2) on files in the artifacts tree, so they hold across processes and, on a
    # shared filesystem that supports them (README: "Running on a cluster"), across hosts.
    def lock(self):
        """Exclusive, for gc: refused while a run of the scene is in progress (gc deletes versions
        that a run may be using before its pointers name them)."""
        return _flock(self.scene_dir / ".lock", fcntl.LOCK_EX,
                      busy=f"a run on {self.scene_dir} is in progress; gc deletes versions a run may be using: "
                           "wait for it to finish")

    def in_use(self):
        """Shared, held by a run for its whole length: runs of one scene go side by side, gc waits."""
        return _flock(self.scene_dir / ".lock", fcntl.LOCK_SH, waiting=f"waiting for gc on {self.scene_dir}")

    def computing(self, stage: str, fingerprint: str):
        """Exclusive lock of one version: two runs never compute it both; the second waits, then
        finds it complete."""
        return _flock(self.scene_dir / ".locks" / f"{stage}-{fingerprint}", fcntl.LOCK_EX,
                      waiting=f"[{stage}] another run is computing {fingerprint}; waiting for it")

    def moving_pointers(self):
        """Exclusive and brief: a run moves all its pointers at once, so they name one run's versions."""
        return _flock(self.scene_dir / ".locks" / "pointers", fcntl.LOCK_EX)


def _process() -> str:
    """Names this process's temporary files; with the host, as a shared tree sees several hosts' pids."""
    return f"{socket.gethostname()}-{os.getpid()}"


@contextlib.contextmanager
def _flock(path: Path, how: int, busy: str | None = None, waiting: str | None = None):
    """Hold flock `how` on `path`. When another process holds it: raise `busy` if given, else say
    `waiting` (if given) and wait."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        try:
            fcntl.flock(f, how | fcntl.LOCK_NB)
        except BlockingIOError:
            if busy:
                raise PipelineError(busy) from None
            if waiting:
                print(waiting, file=sys.stderr)
            fcntl.flock(f, how)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


class RunReport(dict):
    """What `run` did: stage -> 'computed' | 'reused', and ``fingerprints``: stage -> the version it
    used. Read a run's results by these, not by `current`: concurrent runs of a scene move the pointers."""

    def __init__(self):
        super().__init__()
        self.fingerprints: dict[str, str] = {}


# ---------------------------------------------------------------------------- running


class _PeakMemory:
    """Samples this process's RSS in a thread: the peak over one stage (MiB)."""

    def __init__(self, interval: float = 0.1):
        import psutil

        self.proc = psutil.Process()
        self.peak = self.proc.memory_info().rss
        self.interval = interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self):
        while not self._stop.wait(self.interval):
            self.peak = max(self.peak, self.proc.memory_info().rss)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.proc.memory_info().rss)


class Context:
    """What a stage's ``run(ctx)`` sees; see docs/STAGES.md."""

    def __init__(self, stage: Stage, resolved: dict, store: Store, upstream_fps: dict, out: Path, scene, log,
                 fingerprint: str = "unversioned"):
        self.stage = stage
        self.params = resolved[stage.sections[0]]
        self._resolved = resolved
        self._store = store
        self._upstream = upstream_fps
        self.out = out
        self.log_path = out / LOG  # where native libraries' output goes too (io.native_output_to)
        self.scene = scene.name
        self.scene_ref = scene
        self.log = log
        self.metrics: dict = {}
        # Survives a failed or interrupted run of this exact version, so long trainings resume;
        # deleted once the version is published.
        self.checkpoint_dir = store.stage_dir(stage.name) / f".ckpt-{fingerprint}"

    def section(self, name: str):
        reads = self.stage.reads()
        if name not in reads:
            raise PipelineError(f"stage {self.stage.name} reads section {name!r} without declaring it in SECTIONS")
        keys = reads[name]
        return self._resolved[name] if keys is None else DeclaredKeys(self.stage.name, name, self._resolved[name], keys)

    def input(self, name: str) -> Path:
        if name not in self._upstream:
            raise PipelineError(f"stage {self.stage.name} may only read its declared upstream {sorted(self._upstream)}, not {name!r}")
        return self._store.version_dir(name, self._upstream[name])

    def progress(self, iterable=None, **kwargs):
        from tqdm import tqdm

        kwargs.setdefault("desc", self.stage.name)
        kwargs.setdefault("leave", False)
        kwargs.setdefault("dynamic_ncols", True)
        return tqdm(iterable, **kwargs)


def _library_versions() -> dict:
    out = {"python": sys.version.split()[0]}
    for name in LIBRARIES:
        mod = sys.modules.get(name)
        if mod is not None:
            out[name] = getattr(mod, "__version__", "?")
    return out


def _stage_logger(stage: str, path: Path) -> tuple[logging.Logger, list[logging.Handler]]:
    """The stage's logger; the handlers sit on the package logger, so messages of the
    `manifoldneus.*` modules a stage calls (training progress, rollbacks) land in log.txt too,
    and its warnings on the console as well."""
    package = logging.getLogger("manifoldneus")
    package.setLevel(logging.INFO)
    to_file = logging.FileHandler(path)
    to_file.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    to_console = logging.StreamHandler(sys.stderr)
    # warnings only: a failure reaches the console once, as the CLI's one-line error
    to_console.addFilter(lambda record: record.levelno == logging.WARNING)
    to_console.setFormatter(logging.Formatter(f"[{stage}] warning: %(message)s"))
    for h in (to_file, to_console):
        package.addHandler(h)
    return logging.getLogger(f"manifoldneus.{stage}"), [to_file, to_console]


def _detach(handlers: list[logging.Handler]) -> None:
    for h in handlers:
        logging.getLogger("manifoldneus").removeHandler(h)
        try:
            h.close()
        except OSError:  # a log that cannot be flushed (a full disk) must not hide the stage's own error
            pass


def execute(stage: Stage, resolved: dict, store: Store, fps: dict, scene) -> Path:
    """Run one stage into a temporary folder, then rename it into place."""
    fp = fps[stage.name]["fingerprint"]
    final = store.version_dir(stage.name, fp)
    tmp = store.stage_dir(stage.name) / f".tmp-{fp}-{_process()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    log, handlers = _stage_logger(stage.name, tmp / LOG)
    ctx = Context(stage, resolved, store, fps[stage.name]["upstream"], tmp, scene, log, fp)
    log.info("stage %s, scene %s, fingerprint %s", stage.name, scene.name, fp)
    started = time.time()
    cpu0 = time.process_time()
    try:
        with _PeakMemory() as mem:
            stage.module.run(ctx)
        missing = [o for o in stage.outputs if not (tmp / o).exists()]
        if missing:
            raise PipelineError(f"stage {stage.name} did not write its declared outputs {missing}")
        manifest = {
            "stage": stage.name,
            "scene": scene.name,
            "fingerprint": fp,
            "profile": resolved["_profile"],
            "preset": resolved["_preset"],
            "params": fps[stage.name]["params"],
            "code": fps[stage.name]["code"],
            "upstream": fps[stage.name]["upstream"],
            "upstream_content": fps[stage.name]["upstream_content"],
            "inputs": fps[stage.name].get("inputs"),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(started)),
            "wall_seconds": round(time.time() - started, 3),
            "cpu_seconds": round(time.process_time() - cpu0, 3),
            "peak_rss_mib": round(mem.peak / 2**20, 1),
            "libraries": _library_versions(),
            "metrics": ctx.metrics,
            "outputs": sorted(p.name for p in tmp.iterdir() if p.name not in (MANIFEST,)),
        }
        manifest["files"] = file_digests(tmp)
        manifest["content"] = content_digest(manifest["files"])
        log.info("done in %.1f s, peak %.0f MiB", manifest["wall_seconds"], manifest["peak_rss_mib"])
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, default=str) + "\n")
    except BaseException as e:
        log.exception("stage %s failed; nothing was published", stage.name)
        _detach(handlers)
        failed = store.stage_dir(stage.name) / f".failed-{fp}"
        shutil.rmtree(failed, ignore_errors=True)
        tmp.rename(failed)  # kept for its log.txt; never looks complete (no rename to the fingerprint)
        e.stage_failed = (stage.name, failed / LOG)  # for the one-line error of the CLI
        raise
    _detach(handlers)
    if final.exists():  # an older incomplete or forced-over version
        shutil.rmtree(final)
    tmp.rename(final)
    shutil.rmtree(ctx.checkpoint_dir, ignore_errors=True)
    return final


def cli_hint(command: str, scene_name: str, *words: str, artifacts: Path = DEFAULT_ARTIFACTS, data_root=None,
             params_path: Path = DEFAULT_PARAMS, profile=None, preset=None, overrides=()) -> str:
    """A command to print as advice: shell-quoted, with the options that select this run's artifacts,
    data and parameters (so that pasting it acts on the same versions)."""
    args = ["python", "pipeline.py", command, "--scene", scene_name]
    if Path(artifacts).resolve() != DEFAULT_ARTIFACTS.resolve():
        args += ["--artifacts", str(artifacts)]
    if data_root is not None:
        args += ["--data-root", str(data_root)]
    if command == "run":
        if Path(params_path).resolve() != DEFAULT_PARAMS.resolve():
            args += ["--params", str(params_path)]
        if profile:
            args += ["--profile", profile]
        for override in overrides:
            args += ["--set", override]
    if preset:
        args += ["--preset", preset]
    return shlex.join([*args, *words])


def _refuse_damaged(store: Store, stage: str, fingerprint: str, rebuild: str) -> None:
    """``rebuild``: the command that recomputes it (:func:`cli_hint`)."""
    problems = store.damage(stage, fingerprint)
    if problems:
        raise PipelineError(f"{stage} version {fingerprint} is damaged ({problems[0]}"
                            f"{f', and {len(problems) - 1} more' if len(problems) > 1 else ''}); rebuild it: {rebuild}")


def upstream_closure(stages: dict[str, Stage], name: str) -> set[str]:
    """`name` and every stage it depends on, directly or through others."""
    out, todo = set(), [name]
    while todo:
        current = todo.pop()
        if current not in out:
            out.add(current)
            todo.extend(stages[current].upstream)
    return out


def select(stages: dict[str, Stage], until: str | None, only: str | list[str] | None) -> list[str]:
    """The stages a run brings up to date, in DAG order: all; `until` and what it depends on (not
    the stages listed before it that it does not need); or `only` (one stage, or several whose
    upstream are among them or computed)."""
    names = list(stages)
    only_list = [only] if isinstance(only, str) else list(only or [])
    for flag, value in (("--until", until), *(("--only", o) for o in only_list)):
        if value is not None and value not in stages:
            raise PipelineError(f"unknown stage {value!r} for {flag} (stages: {', '.join(names)})")
    if only_list:
        return [n for n in names if n in only_list]
    if until:
        needed = upstream_closure(stages, until)
        return [n for n in names if n in needed]
    return names


def run(
    scene_name: str,
    until: str | None = None,
    only: str | list[str] | None = None,
    overrides: list[str] = (),
    force: list[str] = (),
    profile: str | None = None,
    preset: str | None = None,
    artifacts: Path = DEFAULT_ARTIFACTS,
    params_path: Path = DEFAULT_PARAMS,
    data_root: Path | None = None,
) -> RunReport:
    """Bring the selected stages up to date. Returns stage -> 'computed' | 'reused' and the versions used.

    Runs of one scene may go side by side (processes, hosts on a shared tree): each version is
    computed under its own lock, and the pointers move together at the end."""
    stages = load_stages()
    for f in force:
        if f not in stages:
            raise PipelineError(f"unknown stage {f!r} for --force (stages: {', '.join(stages)})")
    scene = resolve_scene(scene_name, data_root)
    resolved = resolve_params(stages, params_path, overrides, profile, preset)
    store = Store(artifacts, scene.name, preset)
    own = own_ingredients(stages, resolved, scene)
    selected = select(stages, until, only)
    if any("run" in stages[name].reads() for name in selected):  # before the front-end, not after it
        problem = config.device_problem(resolved["run"].device)
        if problem:
            raise ParamError(f"run.device: {problem}")
    report = RunReport()
    intact: set[tuple[str, str]] = set()  # versions whose files were checked in this run

    def hint(*words: str) -> str:
        return cli_hint("run", scene_name, *words, artifacts=artifacts, data_root=data_root, params_path=params_path,
                        profile=profile, preset=preset, overrides=overrides)

    def refuse_damaged(stage: str, fingerprint: str) -> None:
        if (stage, fingerprint) not in intact:
            _refuse_damaged(store, stage, fingerprint, hint("--until", stage, "--force", stage))
            intact.add((stage, fingerprint))

    def needs_computing(name: str, fp: str) -> bool:
        return name in force or not store.is_complete(name, fp)

    started: dict[str, str] = {}
    with store.in_use():
        try:
            for name in selected:
                stage = stages[name]
                fps = chain_fingerprints(stages, own, store)  # upstream stages just run enter by their content
                fp = fps[name]["fingerprint"]
                started[name] = fp
                store.record_run(started)
                for up in stage.upstream:
                    if up not in selected and not store.is_complete(up, fps[up]["fingerprint"]):
                        raise PipelineError(
                            f"stage {name} needs {up} with the current parameters, which has not been computed; "
                            f"run: {hint('--until', name)}"
                        )
                    refuse_damaged(up, fps[up]["fingerprint"])
                if needs_computing(name, fp):
                    with store.computing(name, fp):
                        if needs_computing(name, fp):  # else another run computed it while this one waited
                            print(f"[{name}] running ({fp}) ...", file=sys.stderr)
                            execute(stage, resolved, store, fps, scene)
                            manifest = store.manifest(name, fp)
                            report[name] = "computed"
                            print(f"[{name}] done in {manifest['wall_seconds']:.1f} s, peak "
                                  f"{manifest['peak_rss_mib']:.0f} MiB", file=sys.stderr)
                if name not in report:
                    refuse_damaged(name, fp)
                    report[name] = "reused"
                    print(f"[{name}] up to date ({fp})", file=sys.stderr)
                report.fingerprints[name] = fp
        finally:  # also after a failure: the stages done so far are current
            with store.moving_pointers():
                for name, fp in report.fingerprints.items():
                    store.set_current(name, fp)
        # only a run that ended normally: after a failure or Ctrl-C the record keeps the checkpoint of
        # the stage in progress through gc, for the same command to resume
        store.end_run()
    return report


# ---------------------------------------------------------------------------- inspection


def run_summary(scene_name: str, report: RunReport, artifacts=DEFAULT_ARTIFACTS, data_root=None,
                preset=None) -> str:
    """What a run did and where its results are: per stage ran / cached and its time, the final
    poses' and held-out views' scores where the scene has ground truth, and the paths to open."""
    store = Store(artifacts, resolve_scene(scene_name, data_root).name, preset)
    version = report.fingerprints
    lines, total = [], 0.0
    for name, how in report.items():
        seconds = store.manifest(name, version[name])["wall_seconds"] if how == "computed" else 0.0
        total += seconds
        lines.append(f"  {name:<18} {'ran' if how == 'computed' else 'cached':<7}"
                     + (f"{seconds:8.1f} s" if how == "computed" else ""))
    ran = sum(how == "computed" for how in report.values())
    out = [f"{store.scene_dir.name}: {len(report)} stages, {ran} ran ({total:.0f} s), {len(report) - ran} cached", *lines]
    if "successors" in report:
        out += posed_lines(store.version_dir("successors", version["successors"]),
                           store.version_dir("schedule", version["schedule"]))
    if "evaluate" in report:
        ev = json.loads((store.version_dir("evaluate", version["evaluate"]) / "evaluation.json").read_text())
        if ev.get("poses"):
            final = ev["poses"][-1]
            rot, centre = final["summary"]["rot_err_deg"], final["summary"].get("center_err_units", {})
            units = ev.get("geometry", {}).get("units", "")
            out.append(f"poses ({final['label']}, {final['n_views']} views, against ground truth after a Sim3): "
                       f"rotation {rot['mean']:.3f} deg mean, {rot['median']:.3f} median; centre "
                       f"{centre.get('mean', float('nan')):.3g} {units}".rstrip())
        if ev.get("intrinsics"):
            out.append(camera_line(ev["intrinsics"]))
        nvs = ev.get("novel_views", {}).get("summary", {})
        if nvs.get("psnr_masked") is not None:
            line = f"held-out views: masked PSNR {nvs['psnr_masked']:.2f} dB, SSIM {nvs.get('ssim_masked', 0):.3f}"
            if nvs.get("aligned_psnr_masked") is not None:
                line += (f" at the Sim3-mapped GT poses; {nvs['aligned_psnr_masked']:.2f} dB, SSIM "
                         f"{nvs.get('aligned_ssim_masked', 0):.3f} after test-time alignment")
            out.append(line)
        geo = ev.get("geometry", {})
        if geo.get("chamfer_units") is not None:
            out.append(f"surface: Chamfer {geo['chamfer_units']:.3g} {geo.get('units', '')} to {geo.get('reference', 'the reference')}")
    if "export" in report and store.current("export"):  # first: what a user takes away, in the input's frame
        export_dir = store.version_dir("export", store.current("export"))
        frame = json.loads((export_dir / "world_from_model.json").read_text())
        where = "the input's world" if frame["frame"] == "input" else "the method's unit-sphere frame"
        out.append(f"result:  {export_dir} (transforms.json, colmap/, mesh.glb, mesh.ply, sparse_points.ply; "
                   f"{where}, {frame['units']})")
        out.append(f"viewer:  python pipeline.py view --scene {scene_name}{f' --preset {preset}' if preset else ''}")
    if "mesh" in report:
        mesh_dir = store.version_dir("mesh", version["mesh"])
        out += [f"mesh:    {mesh_dir / 'mesh.ply'} (the method's unit-sphere frame, no colours)",
                f"cameras: {mesh_dir / 'colmap'} (COLMAP text model, the method's frame)"]
    if "evaluate" in report:
        out.append(f"report:  make report SCENE={scene_name}")
    return "\n".join(out)


def posed_lines(successors_dir: Path, schedule_dir: Path) -> list[str]:
    """How many of the views meant to get a pose got one; a warning naming those that did not."""
    from manifoldneus import io

    schedule = io.load_json(schedule_dir / "schedule.json")
    placed = io.load_arrays(successors_dir / "final" / "poses.zarr", ["placed"])["placed"].astype(bool)
    held = set(schedule["held_out_views"])
    meant = [v for v in schedule["views"] if v["view"] not in held]  # those outside the largest component too
    missing = [v["name"] for v in meant if not placed[v["view"]]]
    line = f"posed:   {len(meant) - len(missing)} of {len(meant)} views" + (
        f" ({len(held)} more held out for evaluation)" if held else "")
    if not missing:
        return [line]
    return [line, f"WARNING: {len(missing)} view(s) got no pose: {', '.join(missing[:8])}"
                  f"{' ...' if len(missing) > 8 else ''} (too few verified matches to the posed views: covisibility.png "
                  f"and the schedule stage's log show which)"]


def camera_line(intrinsics: dict) -> str:
    """One line on the camera the poses ended with (evaluation.json's ``intrinsics``): what it started
    from, and its error where the layout has a calibration."""
    start, final = intrinsics["start"], intrinsics["final"]
    line = (f"camera ({intrinsics['source']}): focal {final['focal_px']:.1f} px, principal point "
            f"({final['principal_point_px'][0]:.1f}, {final['principal_point_px'][1]:.1f})")
    if abs(start["focal_px"] - final["focal_px"]) > 1e-6 or start["principal_point_px"] != final["principal_point_px"]:
        line += (f"; self-calibrated from {start['focal_px']:.1f} px, ({start['principal_point_px'][0]:.1f}, "
                 f"{start['principal_point_px'][1]:.1f})")
    if "focal_err_pct" in final:
        line += f"; ground truth {intrinsics['ground_truth']['focal_px']:.1f} px, {final['focal_err_pct']:.2f} % off"
    return line


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def explain(stage: str, fps: dict, store: Store) -> tuple[str, list[str]]:
    """(state, reasons): state is fresh | stale | cached | missing."""
    expected = fps[stage]["fingerprint"]
    current = store.current(stage)
    if current == expected:
        problems = store.damage(stage, current)
        return ("damaged", [*problems, f"rebuild: run --force {stage}"]) if problems else ("fresh", [])
    if current is None:
        if store.is_complete(stage, expected):
            return "cached", ["a complete version for these parameters exists; `run` reuses it"]
        return "missing", ["never computed"]
    old = store.manifest(stage, current)
    reasons = []
    now_p, old_p = _flatten(fps[stage]["params"]), _flatten(old.get("params", {}))
    for key in sorted(set(now_p) | set(old_p)):
        if now_p.get(key, "<absent>") != old_p.get(key, "<absent>"):
            reasons.append(f"param {key}: {old_p.get(key, '<absent>')!r} -> {now_p.get(key, '<absent>')!r}")
    if old.get("code") != fps[stage]["code"]:
        reasons.append("code of the stage (or a module it uses) changed")
    for up, content in fps[stage]["upstream_content"].items():
        if old.get("upstream_content", {}).get(up) != content:
            reasons.append(f"upstream {up} changed" if not content.startswith("recipe:")
                           else f"upstream {up} is not computed with these parameters")
    if old.get("inputs") != fps[stage].get("inputs"):
        reasons.append("input files changed")
    if store.is_complete(stage, expected):
        reasons.append("a complete version for the new parameters exists and will be reused")
    return "stale", reasons or ["fingerprint differs"]


def status(scene_name, overrides=(), profile=None, preset=None, artifacts=DEFAULT_ARTIFACTS,
           params_path=DEFAULT_PARAMS, data_root=None) -> dict[str, tuple[str, list[str]]]:
    stages = load_stages()
    scene = resolve_scene(scene_name, data_root)
    resolved = resolve_params(stages, params_path, overrides, profile, preset)
    store = Store(artifacts, scene.name, preset)
    fps = compute_fingerprints(stages, resolved, scene, store)
    return {name: explain(name, fps, store) for name in stages}


def verify(scene_name: str, artifacts=DEFAULT_ARTIFACTS, data_root=None, preset=None) -> dict[str, tuple[str, list]]:
    """Re-hash every file of each stage's current version against its manifest: stage -> (state,
    problems), state ok | DAMAGED | unverified (a manifest written before file hashes were
    recorded). Stages with no current version are left out."""
    scene = resolve_scene(scene_name, data_root)
    store = Store(artifacts, scene.name, preset)
    out = {}
    for name in load_stages():
        fp = store.current(name)
        if fp is None:
            continue
        if "files" not in store.manifest(name, fp):
            out[name] = ("unverified", ["its manifest predates file hashes; `run --force` it to record them"])
            continue
        problems = store.damage(name, fp, deep=True)
        out[name] = ("DAMAGED" if problems else "ok", problems)
    return out


def describe_artifact(path: Path) -> list[str]:
    lines = []
    for item in sorted(path.iterdir()):
        if item.suffix == ".zarr":
            import zarr

            group = zarr.open_group(str(item), mode="r")
            lines.append(f"  {item.name}/")
            for name, arr in sorted(group.arrays()):
                lines.append(f"      {name:<20} {str(arr.dtype):<8} {list(arr.shape)}")
            if group.attrs:
                lines.append(f"      attrs: {json.dumps(dict(group.attrs), default=str)[:200]}")
        elif item.is_dir():
            n = sum(1 for _ in item.rglob("*") if _.is_file())
            lines.append(f"  {item.name}/ ({n} files)")
        else:
            lines.append(f"  {item.name:<28} {item.stat().st_size / 1024:9.1f} KiB")
    return lines


def show(scene_name: str, stage: str, artifacts=DEFAULT_ARTIFACTS, data_root=None, preset=None) -> str:
    stages = load_stages()
    if stage not in stages:
        raise PipelineError(f"unknown stage {stage!r} (stages: {', '.join(stages)})")
    scene = resolve_scene(scene_name, data_root)
    store = Store(artifacts, scene.name, preset)
    fp = store.current(stage)
    if fp is None:
        raise PipelineError(f"stage {stage} has no current version for scene {scene.name}; run it first")
    m = store.manifest(stage, fp)
    path = store.version_dir(stage, fp)
    out = [
        f"{stage} @ {fp}   ({path})",
        f"profile {m.get('profile')}, preset {m.get('preset')}, started {m['started']}, "
        f"wall {m['wall_seconds']} s, cpu {m['cpu_seconds']} s, peak {m['peak_rss_mib']} MiB",
        f"upstream: {m['upstream']}",
        "params:",
    ]
    out += [f"  {k} = {v!r}" for k, v in _flatten(m["params"]).items()]
    out.append("metrics:")
    out += [f"  {k} = {v}" for k, v in _flatten(m["metrics"]).items()]
    out.append("files:")
    out += describe_artifact(path)
    return "\n".join(out)


def view(scene_name: str, artifacts=DEFAULT_ARTIFACTS, data_root=None, preset=None, out: Path | None = None,
         max_faces: int | None = None) -> tuple[Path, dict]:
    """Write the viewer page of a scene's run: its ``export`` stage's current version and the
    versions that one was computed from (:meth:`Store.lineage`). Default path:
    ``<artifacts>/<scene>/viewer/viewer.html`` (``viewer@<preset>.html`` for a preset). Returns
    (path, what the page holds: camera counts, triangles, bytes)."""
    from manifoldneus import viewer

    scene = resolve_scene(scene_name, data_root)
    store = Store(artifacts, scene.name, preset)
    versions = store.lineage("export")
    if not versions:
        for_preset = f" --preset {preset}" if preset else ""
        raise PipelineError(f"scene {scene.name}{for_preset} has no exported result to view in {Path(artifacts)}; "
                            f"run: {cli_hint('run', scene_name, artifacts=artifacts, data_root=data_root, preset=preset)}")
    for stage, folder in versions.items():
        _refuse_damaged(store, stage, folder.name, cli_hint("run", scene_name, "--until", stage, "--force", stage,
                                                            artifacts=artifacts, data_root=data_root, preset=preset))
    path = Path(out) if out else store.scene_dir / "viewer" / ("viewer.html" if preset is None else f"viewer@{preset}.html")
    title = scene.name + (f" ({preset})" if preset else "")
    return path, viewer.write_page(versions, path, title, max_faces or viewer.MAX_FACES)


# What gc may delete: names this runner writes inside a stage folder, nothing else.
_VERSION_NAME = re.compile(r"[0-9a-f]{12}")
_LEFTOVER_NAME = re.compile(r"\.(?P<kind>tmp|failed|ckpt)-(?P<fp>[0-9a-f]{12})(?:-(?P<host>.+)-(?P<pid>\d+))?")


def _our_version(stage_dir: Path, folder: Path) -> bool:
    """A version this runner wrote: a real folder named by a fingerprint whose manifest names this
    stage and fingerprint. A folder without such a manifest is not ours to delete."""
    if folder.is_symlink() or not folder.is_dir() or not _VERSION_NAME.fullmatch(folder.name):
        return False
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(manifest, dict) and manifest.get("stage") == stage_dir.name \
        and manifest.get("fingerprint") == folder.name


def _process_alive(host: str | None, pid: str | None) -> bool:
    """Whether the process that names a `.tmp-*` folder may still run. Under gc's exclusive scene
    lock no run holds the scene, so only a live pid of this host (a lock-less filesystem) counts."""
    if host != socket.gethostname() or pid is None:
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _stage_folders(scene_dir: Path, stage_names) -> list[Path]:
    """The scene folder's stage folders (real folders only) that hold a version of ours or, when
    another one does (the scene is ours), the leftovers of our runs only (a killed run's checkpoint)."""
    folders = [d for d in sorted(scene_dir.iterdir()) if d.name in stage_names and d.is_dir() and not d.is_symlink()]
    versions = [d for d in folders if any(_our_version(d, v) for v in d.iterdir())]
    if not versions:
        return []
    return [d for d in folders if d in versions or any(_LEFTOVER_NAME.fullmatch(v.name) for v in d.iterdir())]


def gc_scene_dirs(artifacts: Path, scene_name: str | None = None, data_root=None) -> dict[Path, list[Path]]:
    """The scene folders gc acts on, each with its stage folders that hold versions of ours: the one
    `run` would use for ``scene_name`` (resolved as `run` resolves it), or every folder of the
    artifacts root that holds versions of ours. Only direct children of the artifacts root; nothing
    is created."""
    root = Path(artifacts)
    if not root.is_dir():
        raise PipelineError(f"artifacts folder {root} does not exist: nothing to collect")
    stage_names = set(load_stages())
    if scene_name is None:
        found = {d: _stage_folders(d, stage_names) for d in sorted(root.iterdir()) if d.is_dir() and not d.is_symlink()}
        return {d: stage_dirs for d, stage_dirs in found.items() if stage_dirs}
    scene = resolve_scene(scene_name, data_root)
    scene_dir = root / scene.name
    if scene_dir.is_symlink() or scene_dir.resolve().parent != root.resolve():
        raise PipelineError(f"scene {scene_name!r} maps to {scene_dir}, which is not a folder of {root}: gc leaves it alone")
    stage_dirs = _stage_folders(scene_dir, stage_names) if scene_dir.is_dir() else []
    if not stage_dirs:
        raise PipelineError(f"no artifacts of scene {scene.name!r} in {root} (the scene {scene_name!r} resolves to "
                            f"it as `run` does): nothing to collect")
    return {scene_dir: stage_dirs}


def gc(artifacts: Path = DEFAULT_ARTIFACTS, scene_name: str | None = None, data_root=None,
       dry_run: bool = False, drop_interrupted: bool = False) -> dict[Path, int]:
    """Delete, inside the artifacts root only, the versions this runner wrote that no `current`
    pointer needs (a pointed version keeps the upstream versions it was computed from) and no
    interrupted run would resume from (its record in `.runs/`; ``drop_interrupted`` gives those up
    too), and the leftovers of runs that ended: `.tmp-*` of dead processes, `.failed-*`, and
    checkpoints that no interrupted run resumes (or whose version was published since). Returns
    what it removed (with ``dry_run``, what it would remove): path -> bytes."""
    removed: dict[Path, int] = {}
    for scene_dir, stage_dirs in gc_scene_dirs(artifacts, scene_name, data_root).items():
        store = Store(Path(artifacts), scene_dir.name)
        with store.lock():
            # what the pointers name, and the upstream versions those were computed from: a version
            # reused through the content digest may name an upstream version no pointer names
            todo = [(d.name, os.readlink(p)) for d in stage_dirs for p in d.iterdir()
                    if p.is_symlink() and (p.name == "current" or p.name.startswith("current@"))]
            interrupted = store.interrupted_runs()
            if drop_interrupted:
                for path, _ in interrupted:
                    removed[path] = path.stat().st_size
                    if not dry_run:
                        path.unlink()
                interrupted = []
            resumable = {(stage, fp) for _, record in interrupted for stage, fp in record.get("versions", {}).items()}
            todo += sorted(resumable)
            keep: set[tuple[str, str]] = set()
            while todo:
                stage, fp = todo.pop()
                if (stage, fp) in keep or not store.is_complete(stage, fp):
                    continue
                keep.add((stage, fp))
                todo.extend(store.manifest(stage, fp).get("upstream", {}).items())
            for stage_dir in stage_dirs:
                for entry in sorted(stage_dir.iterdir()):
                    if entry.is_symlink() or not entry.is_dir():
                        continue
                    leftover = _LEFTOVER_NAME.fullmatch(entry.name)
                    if _our_version(stage_dir, entry):
                        doomed = (stage_dir.name, entry.name) not in keep
                    elif leftover and leftover["kind"] == "tmp":
                        doomed = not _process_alive(leftover["host"], leftover["pid"])
                    elif leftover and leftover["kind"] == "failed":
                        doomed = True
                    elif leftover and leftover["kind"] == "ckpt":  # published since, or no run to resume it
                        doomed = (store.is_complete(stage_dir.name, leftover["fp"])
                                  or (stage_dir.name, leftover["fp"]) not in resumable)
                    else:
                        doomed = False  # not a name this runner writes
                    if doomed:
                        removed[entry] = _folder_size(entry)
                        if not dry_run:
                            shutil.rmtree(entry, ignore_errors=True)
            if not dry_run:
                shutil.rmtree(scene_dir / ".locks", ignore_errors=True)  # no run holds one: gc has the scene
    return removed


def _folder_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


# ---------------------------------------------------------------------------- CLI


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pipeline.py", description=__doc__.split("\n")[0])
    p.add_argument("--debug", action="store_true", help="show the traceback of a failure")
    p.add_argument("--version", action="version", version=f"manifoldneus {__version__} (torch "
                   f"{importlib.metadata.version('torch')}, Python {sys.version.split()[0]})")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp, params=True, scenes=False):
        sp.add_argument("--scene", default=None if scenes else "synthetic", action="append" if scenes else "store",
                        help="scene name (synthetic, synthetic-<seed>, scan24, ...) or a folder"
                             + ("; repeat it to run several scenes (default synthetic)" if scenes else ""))
        sp.add_argument("--data-root", type=Path, default=None, help="data root (default $MANIFOLDNEUS_DATA or ../shared/data)")
        sp.add_argument("--artifacts", type=Path, default=DEFAULT_ARTIFACTS,
                        help="the artifacts folder: every stage's versions, per scene (default ./artifacts)")
        if params:
            sp.add_argument("--params", type=Path, default=DEFAULT_PARAMS,
                            help="the parameter file (default ./params.yaml)")
            sp.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                            help="override one parameter for this command (repeat it for several); "
                                 "docs/USAGE.md and `pipeline.py params-diff STAGE` name the keys")
            sp.add_argument("--profile", default=None, help="fast | paper (default: params.yaml's `profile`)")
            sp.add_argument("--preset", default=None, help="a named preset from params.yaml (e.g. neus-barf); "
                                                           "its versions keep their own `current@PRESET` pointers")

    sp = sub.add_parser("run", help="bring stages up to date")
    common(sp, scenes=True)
    executor.add_arguments(sp)
    g = sp.add_mutually_exclusive_group()
    g.add_argument("--until", help="run this stage and the stages it depends on (not the others listed before it)")
    g.add_argument("--only", help="run just this stage (its upstream must be up to date)")
    sp.add_argument("--force", action="append", default=[], metavar="STAGE", help="recompute even if cached")
    sp = sub.add_parser("status", help="which stages are fresh, stale, cached or missing, and why")
    common(sp)
    sp = sub.add_parser("show", help="what a stage's current artifact holds")
    common(sp, params=False)
    sp.add_argument("--preset", default=None, help="the versions of a named preset of params.yaml (its `current@PRESET`)")
    sp.add_argument("stage", help="a stage name (pipeline.py status lists them)")
    sp = sub.add_parser("params-diff", help="what changed since a stage's current version")
    common(sp)
    sp.add_argument("stage", help="a stage name (pipeline.py status lists them)")
    sp = sub.add_parser("verify", help="re-hash the current versions' files against their manifests")
    common(sp, params=False)
    sp.add_argument("--preset", default=None, help="the versions of a named preset of params.yaml (its `current@PRESET`)")
    sp = sub.add_parser("view", help="write the run's viewer page (mesh and cameras in a browser) and print its path")
    common(sp, params=False)
    sp.add_argument("--preset", default=None, help="the versions of a named preset of params.yaml (its `current@PRESET`)")
    sp.add_argument("--out", type=Path, default=None, help="the HTML file (default: <artifacts>/<scene>/viewer/viewer.html)")
    sp.add_argument("--max-faces", type=int, default=None, help="decimate the mesh to at most this many triangles")
    sp.add_argument("--open", action="store_true", help="also open the page in the default browser")
    sp.add_argument("--screenshot", type=Path, default=None, metavar="PNG",
                    help="also render the page in headless Chromium and save what it shows (1200x800)")
    sp = sub.add_parser("gc", help="delete artifact versions no longer current (inside the artifacts folder only)")
    sp.add_argument("--scene", default=None, help="only this scene, resolved as `run` resolves it (default: every scene)")
    sp.add_argument("--data-root", type=Path, default=None, help="data root (default $MANIFOLDNEUS_DATA or ../shared/data)")
    sp.add_argument("--artifacts", type=Path, default=DEFAULT_ARTIFACTS, help="the artifacts folder (default ./artifacts)")
    sp.add_argument("--dry-run", action="store_true", help="list what would be removed, remove nothing")
    sp.add_argument("--drop-interrupted", action="store_true",
                    help="also give up what killed runs left to resume from (their records in <scene>/.runs)")
    return p


def main(argv: list[str] | None = None) -> int:
    """The CLI: every expected failure is one `error:` line and exit code 2 (130 for Ctrl-C);
    ``--debug`` re-raises it with its traceback."""
    args = _parser().parse_args(argv)
    # a log file that cannot be written (a full disk) must not print logging's own tracebacks
    logging.raiseExceptions = bool(args.debug)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        return _command(args)
    except KeyboardInterrupt as e:
        if args.debug:
            raise
        why = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        # on a line of its own, after whatever progress bar was drawing
        print(f"\n{why}: nothing half-written was published; run the same command again to go on "
              "(trainings resume from their checkpoints)", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except (PipelineError, ParamError, SceneError) as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    except PermissionError as e:
        if args.debug:
            raise
        print(f"error: no permission to write {e.filename}: choose a writable artifacts folder with --artifacts DIR",
              file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - a stage's failure: one line, the traceback is in its log
        if args.debug:
            raise
        stage, log_path = getattr(e, "stage_failed", (None, None))
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            print(f"error: {f'stage {stage}: ' if stage else ''}no space left on the disk writing "
                  f"{e.filename or '?'}; nothing was published"
                  f"{f' (what it had written: {log_path.parent})' if log_path else ''}. Free space (python pipeline.py "
                  f"gc drops versions no pointer uses) or run with --artifacts DIR on a larger disk, then the same "
                  f"command again", file=sys.stderr)
            return 2
        where = f"stage {stage} failed: " if stage else ""
        hint = f" (traceback in {log_path}; --debug prints it here)" if log_path else " (--debug prints the traceback)"
        print(f"error: {where}{type(e).__name__}: {e}{hint}", file=sys.stderr)
        return 2


def run_scenes(args) -> int:
    """`run` of one scene here, as before; of several (or with --executor), one task per scene."""
    scenes = list(dict.fromkeys(args.scene or ["synthetic"]))
    kwargs = dict(until=args.until, only=args.only, overrides=args.overrides, force=args.force, profile=args.profile,
                  preset=args.preset, artifacts=args.artifacts, params_path=args.params, data_root=args.data_root)
    if len(scenes) == 1 and args.executor == "in-process":
        print(run_summary(scenes[0], run(scenes[0], **kwargs), args.artifacts, args.data_root, args.preset))
        return 0
    outcomes = []
    for outcome in executor.run_all([executor.RunSpec(s, s, kwargs) for s in scenes], args.executor, args.workers):
        outcomes.append(outcome)
        if outcome.report is not None and not outcome.error:
            print(run_summary(outcome.name, outcome.report, args.artifacts, args.data_root, args.preset) + "\n")
    failed = executor.failures(outcomes)
    if failed:
        print(f"error: {failed}", file=sys.stderr)
    return 1 if failed else 0


def _command(args) -> int:
    if args.command == "run":
        return run_scenes(args)
    elif args.command == "status":
        for name, (state, reasons) in status(args.scene, args.overrides, args.profile, args.preset,
                                             args.artifacts, args.params, args.data_root).items():
            print(f"{name:<18} {state:<8} {'; '.join(reasons)}")
    elif args.command == "show":
        print(show(args.scene, args.stage, args.artifacts, args.data_root, args.preset))
    elif args.command == "params-diff":
        states = status(args.scene, args.overrides, args.profile, args.preset, args.artifacts, args.params,
                        args.data_root)
        if args.stage not in states:
            raise PipelineError(f"unknown stage {args.stage!r} (stages: {', '.join(states)})")
        state, reasons = states[args.stage]
        print(f"{args.stage}: {state}")
        for r in reasons:
            print(f"  {r}")
    elif args.command == "verify":
        results = verify(args.scene, args.artifacts, args.data_root, args.preset)
        for name, (state, problems) in results.items():
            print(f"{name:<18} {state}")
            for problem in problems:
                print(f"    {problem}")
        damaged = [n for n, (state, _) in results.items() if state == "DAMAGED"]
        if damaged:
            forced = [w for name in damaged for w in ("--force", name)]
            print("rebuild: " + cli_hint("run", args.scene, *forced, artifacts=args.artifacts, data_root=args.data_root,
                                         preset=args.preset))
            return 1
    elif args.command == "view":
        path, held = view(args.scene, args.artifacts, args.data_root, args.preset, args.out, args.max_faces)
        decimated = "" if held["faces"] == held["faces_full"] else f" decimated from {held['faces_full']}"
        print(f"{path}  ({held['bytes'] / 2**20:.1f} MiB: {held['optimised']} optimised cameras, "
              f"{held['held_out_drawn']} held-out cameras, mesh of {held['faces']} triangles{decimated})")
        if args.screenshot:
            from manifoldneus import viewer

            shown = viewer.render_in_browser(path, args.screenshot)
            print(f"{args.screenshot}  (the page in headless Chromium: {shown['attributes'].get('cameras-drawn')} "
                  f"cameras drawn{'; page errors: ' + shown['attributes']['errors'] if 'errors' in shown['attributes'] else ''})")
        if args.open:
            import webbrowser

            webbrowser.open(path.resolve().as_uri())
    elif args.command == "gc":
        removed = gc(args.artifacts, args.scene, args.data_root, args.dry_run, args.drop_interrupted)
        verb = "would remove" if args.dry_run else "removed"
        for path, size in removed.items():
            print(f"{verb} {path}  ({size / 2**20:.1f} MiB)")
        print(f"{verb} {len(removed)} old version(s), {sum(removed.values()) / 2**20:.1f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
