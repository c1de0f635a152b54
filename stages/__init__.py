"""The pipeline's stages, in order. Each is one module; see docs/STAGES.md."""
from manifoldneus.config import RunParams, SplitParams

STAGES = [
    "ingest",
    "ground_truth",
]

# The only stages allowed to list `ground_truth` upstream: evaluation, and references labelled as such.
GROUND_TRUTH_READERS = {"evaluate_poses", "evaluate", "reference_surface"}

# Parameter sections used by several stages (a stage's own section is its module's `Params`).
SHARED_SECTIONS = {"run": RunParams, "split": SplitParams}
