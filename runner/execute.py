"""Running stages: the context a stage's ``run(ctx)`` sees, one stage executed into a temporary
folder and published by rename, and `run`, which brings a selection of the DAG up to date."""
from __future__ import annotations

import contextlib
import json
import logging
import shlex
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from manifoldneus import config
from manifoldneus.config import ParamError
from manifoldneus.data.scenes import resolve_scene
from runner.common import DEFAULT_ARTIFACTS, DEFAULT_PARAMS, LOG, MANIFEST, PipelineError
from runner.fingerprint import chain_fingerprints, content_digest, file_digests, own_ingredients
from runner.params import DeclaredKeys, resolve_params
from runner.registry import Stage, for_params, load_stages, select
from runner.store import Store, _process

LIBRARIES = ("numpy", "scipy", "torch", "cv2", "pycolmap", "skimage", "trimesh", "zarr", "roma")


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
        reads = self.stage.keys_read()
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
    log, handlers = logging.getLogger(f"manifoldneus.{stage.name}"), []
    try:
        with _signals_held():  # a Ctrl-C arrives after the folder and its log are set up, inside this `try`
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            log, handlers = _stage_logger(stage.name, tmp / LOG)
        ctx = Context(stage, resolved, store, fps[stage.name]["upstream"], tmp, scene, log, fp)
        log.info("stage %s, scene %s, fingerprint %s", stage.name, scene.name, fp)
        started = time.time()
        cpu0 = time.process_time()
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
        with _signals_held():
            if handlers:  # before the stage's log exists there is nothing to record; the CLI says why
                log.exception("stage %s failed; nothing was published", stage.name)
            _detach(handlers)
            failed = store.stage_dir(stage.name) / f".failed-{fp}"
            shutil.rmtree(failed, ignore_errors=True)
            if tmp.exists():
                tmp.rename(failed)  # kept for its log.txt; never looks complete (no rename to the fingerprint)
        e.stage_failed = (stage.name, failed / LOG)  # for the one-line error of the CLI
        raise
    with _signals_held():  # published whole, or left as the temporary folder the next run replaces
        _detach(handlers)
        if final.exists():  # an older incomplete or forced-over version
            shutil.rmtree(final)
        tmp.rename(final)
    shutil.rmtree(ctx.checkpoint_dir, ignore_errors=True)
    return final


@contextlib.contextmanager
def _signals_held():
    """Ctrl-C and SIGTERM wait until the block is done and arrive right after it, so that the few
    file operations that create or move a version's folder are never cut in half. Python-level
    handlers, not a signal mask: a process-directed signal blocked in the main thread is delivered
    to any other thread (OpenMP's, a timer's), whose flag Python then serves in the main thread
    inside the block anyway. Only the main thread can set handlers; elsewhere the block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum))
                for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        for s in dict.fromkeys(caught):  # each once, in the order they came
            signal.raise_signal(s)


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


def _refuse_damaged(store: Store, stage: str, fingerprint: str, rebuild: str, deep: bool = False) -> None:
    """``rebuild``: the command that recomputes it (:func:`cli_hint`); ``deep``: re-hash the files too."""
    problems = store.damage(stage, fingerprint, deep=deep)
    if problems:
        raise PipelineError(f"{stage} version {fingerprint} is damaged ({problems[0]}"
                            f"{f', and {len(problems) - 1} more' if len(problems) > 1 else ''}); rebuild it: {rebuild}")


def expected_time(store: Store, stages: list[str]) -> str:
    """' (earlier runs: about N min, M min for the run's rest)': the stage's and the remaining ``stages``'
    wall times in this scene's newest versions (an upper bound: some of the rest may be up to date), or ''
    where the scene has no version of the stage yet."""
    first = store.recorded_seconds(stages[0])
    if first is None:
        return ""
    rest = sum(store.recorded_seconds(s) or 0.0 for s in stages)

    def minutes(seconds: float) -> str:
        return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min"

    return f" (earlier runs: about {minutes(first)}" + (f", at most {minutes(rest)} for the run's rest)"
                                                        if len(stages) > 1 else ")")


def run(
    scene_name: str,
    until: str | list[str] | None = None,
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
    stages = for_params(stages, resolved)
    store = Store(artifacts, scene.name, preset)
    own = own_ingredients(stages, resolved, scene)
    selected = select(stages, until, only)
    if any("run" in stages[name].keys_read() for name in selected):  # before the front-end, not after it
        problem = config.device_problem(resolved["run"].device)
        if problem:
            raise ParamError(f"run.device: {problem}")
    report = RunReport()
    intact: set[tuple[str, str, bool]] = set()  # versions whose files were checked in this run (deep: re-hashed)

    def hint(*words: str) -> str:
        return cli_hint("run", scene_name, *words, artifacts=artifacts, data_root=data_root, params_path=params_path,
                        profile=profile, preset=preset, overrides=overrides)

    def refuse_damaged(stage: str, fingerprint: str, deep: bool = False) -> None:
        if (stage, fingerprint, True) not in intact and (stage, fingerprint, deep) not in intact:
            _refuse_damaged(store, stage, fingerprint, hint("--until", stage, "--force", stage), deep)
            intact.add((stage, fingerprint, deep))

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
                    # a stage about to compute re-hashes what it reads: a flipped byte keeps a file's size
                    refuse_damaged(up, fps[up]["fingerprint"], deep=needs_computing(name, fp))
                if needs_computing(name, fp):
                    with store.computing(name, fp):
                        if needs_computing(name, fp):  # else another run computed it while this one waited
                            print(f"[{name}] running ({fp}) ...{expected_time(store, selected[selected.index(name):])}",
                                  file=sys.stderr)
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
