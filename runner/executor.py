"""Multi-run commands (bench, sweep, a run of several scenes) in this process or on Dask distributed.

A command lists its pipeline runs as `RunSpec`s; `run_all` runs them and yields one `Outcome` per
run as it completes. Stages that two or more runs of a scene share (same parameters, code and
upstream: one version) are computed first, once per scene, by one preparation task; then the
runs fan out. Each version is computed under its own lock (`runner.Store.computing`), so two
tasks never compute one version, and a rerun reuses what the cache holds. A run that fails is an
outcome with an error, named on its progress line; the others go on.

Executors (``--executor``): ``in-process`` (the default: one run after the other, here),
``dask`` (a LocalCluster on this machine), ``dask://HOST:PORT`` (an existing scheduler),
``slurm`` or ``slurm:CONFIG`` (dask-jobqueue's SLURMCluster, configured in dask's ``jobqueue.slurm``
or ``jobqueue.CONFIG`` config).
Workers run on the artifacts root given once, which every worker and the client must see at the
same path (README: "Running on a cluster"). Runs with ``run.device=cuda`` ask for a ``GPU``
worker resource on a scheduler or SLURM cluster, so a mixed cluster places them on GPU workers.
"""
from __future__ import annotations

import contextlib
import io
import os
import sys
import threading
import time
import traceback
import uuid
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import runner

EXECUTORS = ("in-process (default) | dask (a LocalCluster here) | dask://HOST:PORT (an existing scheduler) | "
             "slurm[:CONFIG] (dask-jobqueue's SLURMCluster, from dask's jobqueue.slurm config or jobqueue.CONFIG)")
GIB_PER_RUN = 3  # a scan24 run peaks at 2.4 GiB: what a LocalCluster leaves each worker


@dataclass(frozen=True)
class RunSpec:
    """One pipeline run of a multi-run command."""

    name: str    # in progress lines, failures and results
    scene: str
    args: dict   # `runner.run`'s keyword arguments besides the scene: overrides, preset, until, artifacts, ...


@dataclass
class Outcome:
    name: str
    report: dict | None = None   # runner.RunReport: stage -> computed | reused, and its `fingerprints`
    computed: set = field(default_factory=set)  # (stage, fingerprint) of each version it computed
    error: str | None = None     # one line; the run's traceback is in `traceback` (and a stage's in its log.txt)
    traceback: str = ""
    wall_seconds: float = 0.0
    where: str = "in-process"    # the worker that ran it
    console: str = ""            # what the run printed, on a worker (this process's runs print as usual)
    preparation: bool = False    # a scene's shared stages, not one of the command's runs


def add_arguments(parser) -> None:
    """The options every multi-run command shares."""
    parser.add_argument("--executor", default="in-process", type=_executor, metavar="EXECUTOR", help=EXECUTORS)
    parser.add_argument("--workers", type=int, default=None,
                        help="dask / slurm: how many single-threaded workers to start (default: as many as the "
                             f"runs, the CPU cores and {GIB_PER_RUN} GiB of free memory each allow)")


def _executor(text: str) -> str:
    import argparse

    if text not in ("in-process", "dask", "slurm") and not text.startswith(("dask://", "slurm:")):
        raise argparse.ArgumentTypeError(f"unknown executor {text!r}: {EXECUTORS}")
    return text


# ---------------------------------------------------------------------------- planning


@dataclass
class _Plan:
    preparations: dict[tuple, list[tuple[RunSpec, list[str]]]]  # (artifacts, scene) -> (spec, shared stages) in order
    shared: dict[str, set[str]] = field(default_factory=dict)   # run name -> its stages shared with another run
    gpu: dict[str, bool] = field(default_factory=dict)          # run name -> run.device is cuda
    scene_of: dict[str, tuple] = field(default_factory=dict)    # run name -> (artifacts, scene)


def _recipes(spec: RunSpec) -> tuple[tuple, dict[str, str], bool]:
    """((artifacts, scene), stage -> recipe of each stage the run brings up to date, wants a GPU).
    A recipe is the fingerprint with upstream stages entered by their recipes (no store): runs with
    equal recipes for a stage need one version of it."""
    a = spec.args
    stages = runner.load_stages()
    resolved = runner.resolve_params(stages, a.get("params_path", runner.DEFAULT_PARAMS), a.get("overrides", ()),
                                       a.get("profile"), a.get("preset"))
    stages = runner.for_params(stages, resolved)
    scene = runner.resolve_scene(spec.scene, a.get("data_root"))
    fps = runner.compute_fingerprints(stages, resolved, scene)
    selected = runner.select(stages, a.get("until"), a.get("only"))
    where = (str(os.path.abspath(a.get("artifacts", runner.DEFAULT_ARTIFACTS))), scene.name)
    return where, {s: fps[s]["fingerprint"] for s in selected}, resolved["run"].device.startswith("cuda")


def plan(specs: list[RunSpec]) -> _Plan:
    """Which stages are shared, and by whom (every parameter is checked here, before anything runs)."""
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"two runs share a name: {sorted(n for n in names if names.count(n) > 1)}")
    recipes = {spec.name: _recipes(spec) for spec in specs}
    uses = Counter((where, stage, recipe) for where, stages, _ in recipes.values() for stage, recipe in stages.items())
    result, prepared = _Plan({}), set()
    for spec in specs:
        where, stages, gpu = recipes[spec.name]
        shared = [s for s, r in stages.items() if uses[(where, s, r)] > 1]
        todo = [s for s in shared if (where, s, stages[s]) not in prepared]
        prepared |= {(where, s, stages[s]) for s in todo}
        if todo:
            result.preparations.setdefault(where, []).append((spec, todo))
        result.shared[spec.name], result.gpu[spec.name], result.scene_of[spec.name] = set(shared), gpu, where
    return result


# ---------------------------------------------------------------------------- tasks

# A run sets process-wide state (torch's thread count, the stages' log handlers, the console it
# captures): runs in one process, e.g. on a worker with several threads, go one at a time.
_ONE_RUN_AT_A_TIME = threading.Lock()


def _run(name: str, calls: list[tuple[str, dict]], capture: bool, preparation: bool = False,
         after: Outcome | None = None) -> Outcome:
    """Task: `runner.run(scene, **args)` for each call, in order; never raises (a failure is the outcome's)."""
    if after is not None and after.error:
        return Outcome(name, error=f"its scene's shared stages failed: {after.error}")
    out = Outcome(name, where=_worker_address(), preparation=preparation)
    console = io.StringIO()
    started = time.time()
    with _ONE_RUN_AT_A_TIME:
        try:
            with contextlib.ExitStack() as stack:
                if capture:
                    stack.enter_context(contextlib.redirect_stdout(console))
                    stack.enter_context(contextlib.redirect_stderr(console))
                for scene, args in calls:
                    out.report = runner.run(scene, **args)
                    out.computed |= {(s, out.report.fingerprints[s]) for s, how in out.report.items() if how == "computed"}
        except Exception as e:  # noqa: BLE001 - one run's failure must not stop the others
            stage, log_path = getattr(e, "stage_failed", (None, None))
            out.error = (f"stage {stage} failed: " if stage else "") + f"{type(e).__name__}: {e}" \
                + (f" (traceback in {log_path})" if log_path else "")
            out.traceback = traceback.format_exc()
    out.wall_seconds, out.console = round(time.time() - started, 1), console.getvalue()
    return out


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):  # not on a Dask worker
        return "in-process"


def _tasks(specs: list[RunSpec], the_plan: _Plan) -> tuple[dict, dict]:
    """(preparation tasks by (artifacts, scene), run tasks by name): each (name, calls, gpu)."""
    preparations = {}
    for where, steps in the_plan.preparations.items():
        calls = [(spec.scene, {**spec.args, "until": None, "only": stages,
                               "force": [f for f in spec.args.get("force", ()) if f in stages]})
                 for spec, stages in steps]
        preparations[where] = (f"shared stages of {where[1]}", calls, any(the_plan.gpu[s.name] for s, _ in steps))
    runs = {}
    for spec in specs:
        # a forced stage that runs share was recomputed once, by the preparation
        force = [f for f in spec.args.get("force", ()) if f not in the_plan.shared[spec.name]]
        runs[spec.name] = (spec.name, [(spec.scene, {**spec.args, "force": force})], the_plan.gpu[spec.name])
    return preparations, runs


# ---------------------------------------------------------------------------- running


def run_all(specs: list[RunSpec], executor: str = "in-process", workers: int | None = None) -> Iterator[Outcome]:
    """Run every spec; yield each run's outcome (and each preparation's) as it completes, after
    printing its progress line."""
    _executor(executor)
    the_plan = plan(specs)
    preparations, runs = _tasks(specs, the_plan)
    total = len(preparations) + len(runs)
    progress = _Progress(total)
    if executor == "in-process":
        done = {}
        for where, (name, calls, _) in preparations.items():
            done[where] = _run(name, calls, capture=False, preparation=True)
            yield progress.report(done[where])
        for name, calls, _ in runs.values():
            yield progress.report(_run(name, calls, capture=False, after=done.get(the_plan.scene_of[name])))
        return
    from distributed import as_completed

    with _client(executor, workers, len(runs)) as (client, gpu_resources):
        names = {}  # task key -> name, for a task whose worker died

        def submit(name, calls, gpu, **kwargs):
            future = client.submit(_run, name, calls, True, key=f"{name}-{uuid.uuid4().hex[:8]}", pure=False,
                                   resources={"GPU": 1} if gpu and gpu_resources else None, **kwargs)
            names[future.key] = name
            return future

        if gpu_resources and any(gpu for *_, gpu in runs.values()) and not _workers_with_gpu(client):
            print("dask: no worker offers a GPU resource yet; the cuda runs wait for one "
                  "(start GPU workers with --resources GPU=1)", file=sys.stderr)
        # a run waits for its scene's preparation: Dask passes the preparation's outcome in
        prepared = {where: submit(*task, preparation=True) for where, task in preparations.items()}
        futures = [submit(*task, after=prepared.get(the_plan.scene_of[name])) for name, task in runs.items()]
        for future in as_completed([*prepared.values(), *futures]):
            if future.status == "finished":
                outcome = future.result()
            else:  # the worker died (memory, a crash) and Dask gave up on the task
                error = future.exception()
                outcome = Outcome(names[future.key], error=f"{type(error).__name__}: {error}", where="dask")
            yield progress.report(outcome)


class _Progress:
    """One line per task on the console, warnings of runs on workers below it."""

    def __init__(self, total: int):
        self.total, self.done = total, 0

    def report(self, outcome: Outcome) -> Outcome:
        self.done += 1
        status = f"FAILED: {outcome.error}" if outcome.error else "done"
        print(f"[{self.done}/{self.total}] {outcome.name}: {status} ({outcome.wall_seconds:.0f} s, {outcome.where})",
              file=sys.stderr)
        for line in outcome.console.splitlines():
            if "warning:" in line:
                print(f"    {line.strip()}", file=sys.stderr)
        return outcome


def default_workers(runs: int) -> int:
    import psutil

    memory = int(psutil.virtual_memory().available / 2**30 // GIB_PER_RUN)
    return max(1, min(runs, len(os.sched_getaffinity(0)), memory))


@contextlib.contextmanager
def _client(executor: str, workers: int | None, runs: int):
    """(a Dask client, whether tasks ask for GPU resources). One thread per worker: see _ONE_RUN_AT_A_TIME.
    A LocalCluster's workers all see this machine's GPUs, so tasks ask for none there."""
    from distributed import Client, LocalCluster

    if executor.startswith("dask://"):
        with Client("tcp://" + executor[len("dask://"):]) as client:
            print(f"dask: scheduler {client.scheduler.address}, {len(client.scheduler_info()['workers'])} workers, "
                  f"dashboard {client.dashboard_link}", file=sys.stderr)
            yield client, True
        return
    if executor.startswith("slurm"):
        from dask_jobqueue import SLURMCluster  # optional: pip install dask-jobqueue

        # cores, memory, queue, ... from dask's config: jobqueue.slurm, or jobqueue.CONFIG (README)
        cluster = SLURMCluster(config_name=executor.partition(":")[2] or None)
        cluster.scale(workers or runs)
        gpu_resources = True
    else:
        n = workers or default_workers(runs)
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, dashboard_address=":0")
        gpu_resources = False
    with cluster, Client(cluster) as client:
        print(f"dask: {type(cluster).__name__}, {workers or len(cluster.workers)} workers x 1 thread, "
              f"dashboard {client.dashboard_link}", file=sys.stderr)
        yield client, gpu_resources


def _workers_with_gpu(client) -> list[str]:
    return [a for a, w in client.scheduler_info()["workers"].items() if w.get("resources", {}).get("GPU")]


def failures(outcomes: list[Outcome]) -> str:
    """A closing line that names every failed run ('' when none failed)."""
    failed = [o for o in outcomes if o.error]
    if not failed:
        return ""
    return f"{len(failed)} of {len(outcomes)} failed: " + "; ".join(f"{o.name} ({o.error})" for o in failed)

