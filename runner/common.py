"""What every part of the runner shares: where the project and its defaults are, the file names of a
version, and the runner's user-facing errors."""
from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent  # the project: params.yaml, stages/, manifoldneus/
# a clone (an editable install included), else a copy pip installed into site-packages
CHECKOUT = (ROOT / "pyproject.toml").is_file()
# where runs keep their versions unless --artifacts says: set once for a user's runs, from any folder; else
# the clone's artifacts/, or for an installed copy the folder the command runs in
DEFAULT_ARTIFACTS = Path(os.environ.get("MANIFOLDNEUS_ARTIFACTS") or (ROOT if CHECKOUT else Path.cwd()) / "artifacts")
# the clone's params.yaml; an installed copy carries it in this package (runner/params.yaml links to it)
DEFAULT_PARAMS = ROOT / "params.yaml" if CHECKOUT else Path(__file__).with_name("params.yaml")
MANIFEST = "manifest.json"
LOG = "log.txt"


class PipelineError(RuntimeError):
    """A user-facing error: printed as one clear message, without a traceback."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (what `timeout`, SLURM and `kill` send): handled as Ctrl-C is, so the stage in progress
    is moved aside as `.failed-*` and nothing half-written is published."""


def _raise_terminated(signum, frame):
    raise Terminated()
