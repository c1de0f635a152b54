"""The runner: a cached DAG of stages, each writing a versioned artifact.

Dependencies point one way: ``pipeline.py`` (the CLI) -> ``runner`` -> ``stages`` -> ``manifoldneus``.
Inside: registry (the stages and their DAG) -> params -> fingerprint -> store -> execute -> inspect,
and executor (several runs side by side, on Dask) on top.

Artifact layout: ``artifacts/<scene>/<stage>/<fingerprint>/`` (files + ``manifest.json`` +
``log.txt``) and ``artifacts/<scene>/<stage>/current`` (symlink to the version in use).
A fingerprint hashes the parameter keys the stage declares, the source of the stage module
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
import os

# Small dense solves (BA, Umeyama, eigh) are slower with threaded OpenBLAS on a loaded 2-core
# machine than on one thread; torch keeps its own thread pool (run.threads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Busy-waiting OpenMP threads made training steps up to 8x slower when the cores are shared.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import cv2  # noqa: E402,F401  - loads the system zlib before pycolmap's own deflate symbols can shadow it
import pycolmap  # noqa: E402,F401  - imported before main() takes SIGTERM from the failure handler pycolmap installs

from manifoldneus.config import ParamError  # noqa: E402
from manifoldneus.data.scenes import SceneError, resolve_scene  # noqa: E402
from runner.common import DEFAULT_ARTIFACTS, DEFAULT_PARAMS, LOG, MANIFEST, ROOT, PipelineError, Terminated  # noqa: E402
from runner.execute import Context, RunReport, cli_hint, run  # noqa: E402
from runner.fingerprint import code_hash, compute_fingerprints, own_ingredients  # noqa: E402
from runner.inspect import camera_line, posed_lines, run_summary, show, status, verify, view  # noqa: E402
from runner.params import resolve_params, stage_params  # noqa: E402
from runner.registry import Stage, for_params, load_stages, select, upstream_closure  # noqa: E402
from runner.store import Store, gc  # noqa: E402

__all__ = [
    "DEFAULT_ARTIFACTS", "DEFAULT_PARAMS", "LOG", "MANIFEST", "ROOT", "Context", "ParamError", "PipelineError",
    "RunReport", "SceneError", "Stage", "Store", "Terminated", "camera_line", "cli_hint", "code_hash",
    "compute_fingerprints", "for_params", "gc", "load_stages", "own_ingredients", "posed_lines", "resolve_params",
    "resolve_scene", "run", "run_summary", "select", "show", "stage_params", "status", "upstream_closure", "verify",
    "view",
]
