"""The artifact store of one scene: versioned folders, `current` pointers (one per preset), the
records of runs in progress, the locks that let runs go side by side, and gc."""
from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import shutil
import socket
import sys
import time
from pathlib import Path

from manifoldneus.data.io import write_text_atomic
from manifoldneus.data.scenes import resolve_scene
from runner.common import DEFAULT_ARTIFACTS, MANIFEST, PipelineError
from runner.fingerprint import content_digest, sha256_of
from runner.registry import load_stages


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

    def pointed(self, stage: str) -> str | None:
        """The fingerprint the stage's pointer names, complete or not (None: no pointer)."""
        link = self.stage_dir(stage) / self.pointer
        return os.readlink(link) if link.is_symlink() else None

    def current(self, stage: str) -> str | None:
        fp = self.pointed(stage)
        return fp if fp is not None and self.is_complete(stage, fp) else None

    def set_current(self, stage: str, fingerprint: str) -> None:
        tmp = self.stage_dir(stage) / f".current-{_process()}"
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(fingerprint, tmp)
        os.replace(tmp, self.stage_dir(stage) / self.pointer)

    def content(self, stage: str, fingerprint: str, files: tuple[str, ...] | None = None) -> str | None:
        """The content digest of a complete version, or with ``files`` (paths inside it: a file, or a
        folder and what is under it) of those files only (None: absent, unreadable, or written before
        digests)."""
        try:
            manifest = json.loads((self.version_dir(stage, fingerprint) / MANIFEST).read_text())
        except (OSError, ValueError):
            return None
        if files is None or "files" not in manifest:
            return manifest.get("content")
        picked = {rel: rec for rel, rec in manifest["files"].items()
                  if any(rel == f or rel.startswith(f.rstrip("/") + "/") for f in files)}
        return content_digest(picked)

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

    def recorded_seconds(self, stage: str) -> float | None:
        """The wall time of the stage's newest complete version of this scene (any parameters), or None."""
        best = None
        for manifest in self.stage_dir(stage).glob(f"*/{MANIFEST}"):
            try:
                when, seconds = manifest.stat().st_mtime, json.loads(manifest.read_text())["wall_seconds"]
            except (OSError, ValueError, KeyError):
                continue
            if best is None or when > best[0]:
                best = (when, float(seconds))
        return None if best is None else best[1]

    def lineage(self, stage: str, beside: tuple[str, ...] = ()) -> dict[str, Path]:
        """The current version of ``stage`` and the versions of all its upstream stages that it was
        computed from (as its manifests name them): one consistent set, whatever the other stages'
        pointers say now; and the current version of each stage of ``beside`` that is not among them
        (e.g. pycolmap's reference, which a run reads only for what is beside its result). Stage ->
        version folder; {} when ``stage`` has no current version."""
        fp = self.current(stage)
        todo, out = ([(stage, fp)] if fp else []), {}
        while todo:
            name, fp = todo.pop()
            if name in out:
                continue
            out[name] = self.version_dir(name, fp)
            todo.extend(self.manifest(name, fp).get("upstream", {}).items())
        for name in beside:
            if out and name not in out and self.current(name):
                out[name] = self.version_dir(name, self.current(name))
        return out

    # A run's record: the versions it has started or finished, written as it goes. A run that does
    # not end normally (a failure, Ctrl-C, SIGKILL, a lost node) leaves it, so that gc keeps what
    # running the same command again resumes from (its finished versions and its checkpoints).
    def record_run(self, versions: dict[str, str]) -> None:
        path = self.scene_dir / ".runs" / f"{_process()}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps({"pointer": self.pointer, "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
                                            "versions": versions}))

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
