"""The pipeline's stages, in order. Each is one module; see docs/STAGES.md."""
from manifoldneus.config import RunParams, SplitParams
from manifoldneus.sfm.correspondence import CorrespondenceParams
from manifoldneus.output.evaluation import MeshParams, NovelViewParams
from manifoldneus.neural.field import FieldParams
from manifoldneus.neural.gate import GateParams
from manifoldneus.neural.losses import LossParams
from manifoldneus.neural.render import RenderParams
from manifoldneus.neural.train import TrainParams

STAGES = [
    "ingest",
    "ground_truth",
    "features",
    "matching",
    "covisibility",
    "spectral",
    "schedule",
    "reference",
    "evaluate_poses",
    "reference_surface",
    "anchors",
    "successors",
    "surface",
    "mesh",
    "evaluate",
    "export",
]

# The only stages allowed to list `ground_truth` upstream: evaluation, references labelled as such, and
# the export, which takes only the input's world frame from it (stages/export.py).
GROUND_TRUTH_READERS = {"evaluate_poses", "evaluate", "reference_surface", "export"}

# Parameter sections used by several stages (a stage's own section is its module's `Params`).
SHARED_SECTIONS = {
    "run": RunParams,
    "split": SplitParams,
    "train": TrainParams,
    "field": FieldParams,
    "render": RenderParams,
    "loss": LossParams,
    "gate": GateParams,
    "correspondence": CorrespondenceParams,
    "meshing": MeshParams,
    "novel_views": NovelViewParams,
}
