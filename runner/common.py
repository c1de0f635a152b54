"""What every part of the runner shares: where the project and its defaults are, the file names of a
version, and the runner's user-facing errors."""
from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent  # the project: params.yaml, stages/, manifoldneus/
# where runs keep their versions unless --artifacts says: set once for a user's runs, from any folder
DEFAULT_ARTIFACTS = Path(os.environ.get("MANIFOLDNEUS_ARTIFACTS") or ROOT / "artifacts")
DEFAULT_PARAMS = ROOT / "params.yaml"
MANIFEST = "manifest.json"
LOG = "log.txt"


class PipelineError(RuntimeError):
    """A user-facing error: printed as one clear message, without a traceback."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (what `timeout`, SLURM and `kill` send): handled as Ctrl-C is, so the stage in progress
    is moved aside as `.failed-*` and nothing half-written is published."""


def _raise_terminated(signum, frame):
    raise Terminated()
