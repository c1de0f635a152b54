"""anchors: initial poses of the anchor views, then joint field + pose optimisation on them.

Pose initialisation (``anchors.pose_init``):
- ``matches`` (default): the front-end's keypoints and verified matches of the anchors (and of the
  views that bridge them) handed to COLMAP's incremental mapper and bundle adjustment, then the
  unit-sphere gauge (:func:`manifoldneus.sfm.pose_init.init_from_matches`); COLMAP's log goes to log.txt;
- ``identity``: every anchor at one canonical pose looking at the origin (the paper's wording);
- ``reference``: the pycolmap reference poses (the `neus-colmap` preset), gauged the same way;
- ``input``: the poses of the scene's own COLMAP model (``sparse/0`` beside ``images/``), gauged the same way,
  with its cameras' intrinsics (ingest's K); the other views join as with any start.
Intrinsics that are a guess or an EXIF prior (``anchors.intrinsics``) are first self-calibrated: one
shared camera's focal length, principal point and radial lens distortion refined by COLMAP on every
trainable view's matches (:func:`self_calibrate`; the principal point and the distortion only where a
likelihood-ratio test says they pay), then held fixed from the anchors' initialisation on. A distortion
found there is removed from the images, masks and keypoints of every later stage (they work with
pinhole cameras; :func:`manifoldneus.posefree.with_intrinsics`).
Writes ``round_0/`` (see :mod:`manifoldneus.posefree`) and ``initial_poses.zarr``: the anchors' initial
poses, their K and lens ``distortion`` [N,4] (OpenCV's, where one was found), the object's SfM points (``object_points`` [P,3], gauge frame; the mesh stage's crop
without masks) and the lines of sight of every SfM observation (``sight_lines`` [O,2,3]; free space for
the rounds' training without masks).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.scheduling import mavos
from manifoldneus.sfm import pose_init, mapper as sfm
from manifoldneus import posefree
from manifoldneus.config import ParamError, param


@dataclass
class Params:
    """Section `anchors` of params.yaml."""

    pose_init: str = param("matches", "Initial anchor poses: matches (SfM on the front-end's matches) | identity | "
                           "reference (pycolmap's SfM) | input (the scene's own COLMAP model)",
                           choices=["matches", "identity", "reference", "input"])
    optimise_poses: bool = param(True, "Learn per-view pose corrections (False: keep the initial poses)")
    iters: int = param(1500, "Iterations of the anchor stage", lo=1)
    pose_lr: float = param(8e-3, "Peak AdamW lr of the anchors' pose corrections (supplement: 8e-3)", lo=0.0)
    pose_start_frac: float = param(0.3, "Poses stay frozen for this fraction of the iterations (the field fits first)",
                                   lo=0.0, hi=1.0)
    pose_warmup_frac: float = param(0.1, "Pose lr warm-up as a fraction of the stage (supplement: 2k iterations)",
                                    lo=0.0, hi=1.0)
    correspondence_weight: float = param(1.0, "Weight of the correspondence term (section `correspondence`) in the "
                                         "anchors' pose loss; 0 = photometric poses only (docs/REFINEMENT.md)", lo=0.0)
    intrinsics: str = param("auto", "matches init: fixed holds the ingest's K; refine lets COLMAP's mapper and bundle "
                            "adjustment refine `refine_intrinsics` of each shared camera (one per K and image size), "
                            "and every later stage uses the refined K; auto: fixed for calibrated or given intrinsics "
                            "(views.json intrinsics_source), refine for an EXIF focal length or the 1.2 x guess",
                            choices=["auto", "fixed", "refine"])
    refine_intrinsics: list[str] = param(["focal", "principal_point", "radial"], "What `intrinsics = refine` "
                                         "changes: focal, principal_point, radial (a radial lens distortion k1, "
                                         "COLMAP's SIMPLE_RADIAL, removed from the images before training)")
    principal_point_p: float = param(1e-3, "With principal_point in refine_intrinsics: it is freed only when that "
                                     "lowers the reprojection error significantly, a likelihood-ratio test at this "
                                     "p-value (sfm.free_principal_point; 1 = always freed). A narrow field of view "
                                     "trades it against the rotations: freed on 17 synthetic 192 px views with the "
                                     "true one at the centre, it moved 8 px and the rotations 0.14 -> 0.93 deg",
                                     lo=0.0, hi=1.0)
    radial_p: float = param(1e-3, "With radial in refine_intrinsics: the lens's radial distortion is freed only when "
                            "that lowers the reprojection error significantly, a likelihood-ratio test at this p-value "
                            "(1 = always freed): a lens without distortion keeps k1 = 0 and the images are not "
                            "resampled", lo=0.0, hi=1.0)
    calibrate_on: str = param("trainable", "intrinsics = refine: the views whose bundle adjustment estimates the shared "
                              "camera before the anchors are initialised with it held fixed: trainable (every training "
                              "view) or anchors (the anchors' own initialisation). Measured on scan24_idr's photos "
                              "alone: the 13 anchors moved the principal point the wrong way (rotation 0.67 -> 0.81 "
                              "deg), the 42 training views found it within 3.5 px (0.11 deg)",
                              choices=["trainable", "anchors"])
    sight_lines_from: str = param("anchors", "Without masks, the lines of sight the rounds keep free of surface "
                                  "(loss.w_free_space): anchors (the anchors' initialisation's observations) or "
                                  "calibration (every training view's in the self-calibration's reconstruction, "
                                  "brought onto the anchors' frame by their camera centres; the anchors' own where no "
                                  "self-calibration ran). scan24_idr photos alone, Chamfer seeds 0/1: anchors 5.81 / "
                                  "4.99 mm, calibration 5.62 / 5.82", choices=["anchors", "calibration"])
    reproj_px: float = param(3.0, "matches init: COLMAP's reprojection threshold for keeping observations (px)",
                             lo=0.1)
    ba_loss: str = param("cauchy", "matches init: robust loss of a last bundle adjustment after COLMAP's mapper (its own "
                         "global adjustments are plain least squares); trivial = none. Measured on synthetic, scan24 "
                         "and scan24_idr (bench/bench_init.py): cauchy at 0.5 px gave the lowest rotation error",
                         choices=["trivial", "soft_l1", "cauchy", "huber"])
    ba_loss_px: float = param(0.5, "matches init: scale of that robust loss (px), about twice SIFT's keypoint noise",
                              lo=0.01)
    bridge_min_matches: int = param(50, "matches init: when the anchors' own co-visibility graph is disconnected or "
                                    "its weakest spanning link has fewer verified matches than this, the "
                                    "initialisation also uses the training views that bridge them along the "
                                    "maximum spanning tree of all training views (their poses are not kept); "
                                    "0 = the anchors' own matches only", lo=0)
    gauge_radius: float = param(0.8, "Radius of the sphere the robust box of the anchors' points is scaled into "
                                "(the object in the unit sphere)", lo=0.1, hi=1.0)
    object_min_seen: float = param(0.5, "Without masks, the object's points are those at least this fraction of the "
                                   "registered views see in their frame (the common frustum); the gauge, the grid box "
                                   "and the mesh's crop are taken from them (manifoldneus/geometry/object_region.py)",
                                   lo=0.0, hi=1.0)
    gauge_percentile: float = param(99.0, "The gauge's robust box: per axis, the points between this percentile and "
                                    "100 minus it (the foreground's with masks, else the common frustum's); its half "
                                    "diagonal goes to gauge_radius (manifoldneus.geometry.cameras."
                                    "gauge_from_points)", lo=50.0, hi=100.0)
    gauge_centre: str = param("box", "What goes to the gauge's origin: the middle of the points' robust box, or their "
                              "median (where the views see most) moved towards the box's middle only as far as keeps "
                              "the box inside the unit sphere: better PSNR on DTU, worse Chamfer on scan24 and worse "
                              "photos-alone surfaces (docs/REFINEMENT.md, \"The gauge's centre\")",
                              choices=["box", "median"])
    identity_distance: float = param(3.0, "identity init: distance of the canonical camera from the origin", lo=0.5)
    perturb_rot_deg: list[float] = param([0.0, 0.0], "Experiments from a perturbed start (BARF): each anchor's initial "
                                         "rotation is turned by an angle drawn from [lo, hi] deg about a random axis "
                                         "(seeded by run.seed); [0, 0] = no perturbation", lo=0.0, hi=90.0)
    perturb_centre_frac: float = param(0.0, "Experiments from a perturbed start: each anchor's initial centre moves "
                                       "by this fraction of the anchors' mean distance from the origin, in a random "
                                       "direction", lo=0.0, hi=1.0)

    def __post_init__(self):
        unknown = set(self.refine_intrinsics) - set(sfm.REFINABLE)
        if unknown:
            raise ParamError(f"anchors.refine_intrinsics: {sorted(unknown)} not among {', '.join(sfm.REFINABLE)}")
        if len(self.perturb_rot_deg) != 2 or self.perturb_rot_deg[0] > self.perturb_rot_deg[1]:
            raise ParamError(f"anchors.perturb_rot_deg: expected [lo, hi] with lo <= hi, got {self.perturb_rot_deg}")


UPSTREAM = ("ingest", "features", "matching", "covisibility", "schedule", "reference")
UPSTREAM_IF = {"reference": ("pose_init", "reference")}  # pycolmap's SfM only where the anchors start from it
SECTIONS = ("anchors", "train", "field", "render", "loss", "gate", "correspondence", "run")
OUTPUTS = (artifacts.ANCHOR_ROUND, artifacts.INITIAL_POSES)


@dataclass
class InitEnv:
    """What the initialisation needs of its run: where it logs, the file COLMAP's own output goes to,
    and the seed of COLMAP's random choices."""

    log: logging.Logger
    log_path: Path
    seed: int


def gauged(w2c: np.ndarray, points: np.ndarray, p: Params) -> np.ndarray:
    """Poses w2c [N,4,4] in the unit-sphere gauge of their SfM's points [P,3] (the camera centres where
    there are fewer than 3)."""
    from manifoldneus.geometry import cameras

    pts = points if len(points) >= 3 else cameras.camera_centers(w2c)
    s, centre = cameras.gauge_from_points(pts, p.gauge_radius, centre=p.gauge_centre)
    return cameras.transform_w2c(w2c, s, np.eye(3), -s * centre)


def reference_poses(reference_dir, p: Params) -> tuple[np.ndarray, np.ndarray]:
    """pycolmap's poses in the unit-sphere gauge of its own points; (w2c [N,4,4], registered [N])."""
    import pycolmap

    from manifoldneus.geometry import cameras

    ref = artifacts.load_reference_poses(reference_dir)
    if not ref["registered"].any():
        raise ParamError("anchors.pose_init = reference: the pycolmap reference registered no view (photos without "
                         "cameras skip it: add --set reference.when=always)")
    rec = pycolmap.Reconstruction(str(reference_dir / "sparse"))
    pts = np.array([pt.xyz for pt in rec.points3D.values()]).reshape(-1, 3)  # [P,3]
    registered = ref["registered"].astype(bool)
    if len(pts) < 3:
        pts = cameras.camera_centers(ref["w2c"][registered])
    return gauged(ref["w2c"], pts, p), registered


def input_poses(ingest_dir: Path, p: Params) -> np.ndarray:
    """The poses of the scene's own COLMAP model (ingest's ``input_cameras.zarr``) in the unit-sphere gauge
    of its points; w2c [N,4,4]."""
    given = artifacts.load_input_cameras(ingest_dir)
    if given is None:
        raise ParamError("anchors.pose_init = input starts from the poses of the scene's own COLMAP model; this "
                         "scene has none (a COLMAP model is a folder with sparse/0/ beside images/): use "
                         "anchors.pose_init = matches")
    return gauged(given["w2c"], given["points"], p)


def initial_poses(env: InitEnv, inputs: posefree.SceneInputs, anchors: list[int], p: Params, reference_dir: Path | None,
                  ingest_dir: Path) -> tuple[np.ndarray, posefree.SceneInputs, dict, dict]:
    """(w2c [N,4,4] of the anchors (identity elsewhere), the inputs with the K and lens distortion the
    poses belong to (:func:`manifoldneus.posefree.with_intrinsics`), what was done,
    the SfM points in the gauge frame: ``object_points`` [P,3] (those in the foreground or the common
    frustum) and ``sight_lines`` [O,2,3] (:func:`sight_lines`); none for the identity and reference
    initialisations)."""
    no_points = {"object_points": np.zeros((0, 3)), "sight_lines": np.zeros((0, 2, 3))}
    n = len(inputs.names)
    w2c = np.tile(np.eye(4), (n, 1, 1))
    K = inputs.views.K
    if p.pose_init == "identity":
        w2c[anchors] = pose_init.identity_init(len(anchors), p.identity_distance)
        return w2c, inputs, {"method": "identity"}, no_points
    if p.pose_init == "input":  # the model's own cameras: ingest's K, held as the model has them
        w2c[anchors] = input_poses(ingest_dir, p)[anchors]
        return w2c, inputs, {"method": "input"}, no_points
    if p.pose_init == "reference":
        ref, registered = reference_poses(reference_dir, p)
        if registered.any():  # pycolmap's intrinsics (refined when it refined them)
            ids = np.flatnonzero(registered)
            ref_K = artifacts.load_reference_poses(reference_dir, ["K"])["K"]
            K = sfm.shared_K(K, inputs.sizes, ids, ref_K[ids])
        missing = [inputs.names[a] for a in anchors if not registered[a]]
        if missing:
            env.log.warning("pycolmap did not register anchors %s; they start at a registered neighbour's pose", missing)
        w2c[anchors] = ref[anchors]
        for a in anchors:
            if not registered[a]:
                nb = [j for j in np.argsort(-inputs.W[a]) if registered[j]]
                w2c[a] = ref[nb[0]] if nb else np.eye(4)
        return w2c, posefree.with_intrinsics(inputs, K), {"method": "reference", "unregistered": missing}, no_points
    inputs, refine, calibration, calibration_rec = calibrated_inputs(env, inputs, p)
    res = matches_init(env, inputs, anchors, p, refine)
    ids = res.view_ids
    bridges = sorted(set(ids) - set(anchors))
    unplaced = [v for v in res.unplaced if v in set(anchors)]
    for v in unplaced:
        env.log.warning("initialisation could not place anchor %s (%s); it starts at a neighbour's pose",
                        inputs.names[v], res.why_unplaced[v])
    row = {v: k for k, v in enumerate(ids)}
    w2c[anchors] = res.w2c[[row[a] for a in anchors]]
    if res.diagnostics["refine_intrinsics"] and res.placed.any():
        K, distortion = estimated_intrinsics(inputs, res)
        log_refined(env, res.diagnostics["refine_intrinsics"], inputs.views.K[anchors[0]], K[anchors[0]],
                    distortion[anchors[0]], "anchors")
        inputs = posefree.with_intrinsics(inputs, K, distortion)
    return w2c, inputs, {"method": "matches", "per_view": {int(a): res.method[row[a]] for a in anchors},
                 "bridges": [int(v) for v in bridges], "unplaced": [inputs.names[v] for v in unplaced],
                 "why_unplaced": {inputs.names[v]: res.why_unplaced[v] for v in unplaced},
                 **res.diagnostics, "calibration": calibration}, {"object_points": res.points[res.point_in_mask],
                                                                  "sight_lines": lines_of_sight(env, res, calibration_rec, p)}


def sight_lines(res: pose_init.InitResult) -> np.ndarray:
    """[O,2,3]: per observation of the reconstruction's points by a placed view, its camera centre and the
    point (gauge frame): the segment between them is free space (:class:`manifoldneus.neural.losses.SightLines`)."""
    from manifoldneus.geometry.cameras import camera_centers

    row = {v: k for k, v in enumerate(res.view_ids)}
    rows = np.array([row[int(v)] for v in res.obs_view], int)
    seen = res.placed[rows] if len(rows) else np.zeros(0, bool)
    return np.stack([camera_centers(res.w2c)[rows[seen]], res.points[res.obs_point[seen]]], 1) if seen.any() \
        else np.zeros((0, 2, 3))


def lines_of_sight(env: InitEnv, res: pose_init.InitResult, calibration: pose_init.InitResult | None, p: Params) -> np.ndarray:
    """The lines of sight (:func:`sight_lines`) in the anchors' gauge frame: the self-calibration's (every
    training view) brought onto it by the similarity between the two reconstructions' common views' camera
    centres, when ``anchors.sight_lines_from`` asks for them and they exist; else the anchors' own."""
    own = sight_lines(res)
    if p.sight_lines_from != "calibration" or calibration is None:
        return own
    from manifoldneus.geometry import cameras

    row = {v: k for k, v in enumerate(calibration.view_ids)}
    common = [(row[v], k) for k, v in enumerate(res.view_ids) if v in row and res.placed[k] and calibration.placed[row[v]]]
    if len(common) < 3:
        env.log.warning("the self-calibration shares %d placed views with the anchors' initialisation: too few to "
                        "bring its lines of sight over; the anchors' own are used", len(common))
        return own
    src, dst = (np.array(c) for c in zip(*common))
    s, R, t = cameras.align_centres(calibration.w2c[src], res.w2c[dst])
    M = cameras.sim3_matrix(s, R, t)
    lines = sight_lines(calibration)
    lines = cameras.transform_points(M, lines.reshape(-1, 3)).reshape(-1, 2, 3)
    gap = np.linalg.norm(cameras.transform_points(M, cameras.camera_centers(calibration.w2c[src]))
                         - cameras.camera_centers(res.w2c[dst]), axis=1)
    env.log.info("lines of sight: %d observations of %d training views (self-calibration), brought onto the anchors' "
                 "frame by %d common views (centres within %.4f, max %.4f); the anchors' own: %d", len(lines),
                 int(calibration.placed.sum()), len(common), gap.mean(), gap.max(), len(own))
    return lines


def estimated_intrinsics(inputs: posefree.SceneInputs, res: pose_init.InitResult) -> tuple[np.ndarray, np.ndarray]:
    """(K [N,3,3], lens distortion [N,4]) of every view: what the reconstruction ``res`` estimated for its
    placed views, given to every view of the same camera (:func:`manifoldneus.sfm.mapper.shared_K`)."""
    placed = [res.view_ids[k] for k in np.flatnonzero(res.placed)]
    K = sfm.shared_K(inputs.views.K, inputs.sizes, placed, res.K[res.placed])
    distortion = sfm.shared_K(inputs.views.K, inputs.sizes, placed, res.distortion[res.placed],
                              values=np.zeros((len(K), 4)))
    return K, distortion


def log_refined(env: InitEnv, refine, K_before: np.ndarray, K_after: np.ndarray, distortion: np.ndarray, views: str) -> None:
    env.log.info("intrinsics refined (%s) on the %s: focal %.1f -> %.1f px, principal point (%.1f, %.1f) -> "
                 "(%.1f, %.1f), radial distortion k1 %.4g", ", ".join(refine), views, K_before[0, 0], K_after[0, 0],
                 *K_before[:2, 2], *K_after[:2, 2], distortion[0])


def calibrated_inputs(env: InitEnv, inputs: posefree.SceneInputs, p: Params
                      ) -> tuple[posefree.SceneInputs, tuple, dict | None, pose_init.InitResult | None]:
    """The `matches` initialisation's intrinsics: (inputs with the self-calibrated K when `calibrate_on`
    is trainable, what the anchors' own bundle adjustment may still refine, the calibration's record and
    reconstruction)."""
    refine = tuple(p.refine_intrinsics) if sfm.intrinsics_mode(p.intrinsics, inputs.intrinsics_source) == "refine" else ()
    if not refine or p.calibrate_on != "trainable":
        return inputs, refine, None, None
    K, distortion, calibration, reconstruction = self_calibrate(env, inputs, refine, p)
    return posefree.with_intrinsics(inputs, K, distortion), (), calibration, reconstruction


def mapper_options(inputs: posefree.SceneInputs, p: Params, seed: int, refine=()) -> pose_init.MapperOptions:
    """COLMAP's mapper as the anchors run it, on the views' intrinsics (``refine``: what it may change)."""
    return pose_init.MapperOptions(refine=tuple(refine), prior_focal=inputs.intrinsics_source != "default",
                                   reproj_px=p.reproj_px, final_ba_loss=p.ba_loss, final_ba_scale_px=p.ba_loss_px,
                                   principal_point_p=p.principal_point_p, radial_p=p.radial_p, seed=seed)


def gauge_options(p: Params) -> pose_init.GaugeOptions:
    """The unit-sphere gauge the anchors fit to their SfM's points (the successors' restart fits the same)."""
    return pose_init.GaugeOptions(p.gauge_radius, p.gauge_percentile, p.gauge_centre, p.object_min_seen)


def self_calibrate(env: InitEnv, inputs: posefree.SceneInputs, refine, p: Params
                   ) -> tuple[np.ndarray, np.ndarray | None, dict, pose_init.InitResult | None]:
    """The shared camera's intrinsics ``refine`` estimated by COLMAP's mapper and bundle adjustment on every
    trainable view's matches (a few anchors at a narrow field of view do not pin the principal point down);
    (K [N,3,3], lens distortion [N,4] or None, what was done, the reconstruction). Its poses are not kept:
    the anchors are initialised afterwards, K fixed, on keypoints without the distortion."""
    ids = [int(v) for v in np.flatnonzero(inputs.train_mask)]
    with io.native_output_to(env.log_path):
        res = pose_init.init_from_matches(ids, inputs.views.K, inputs.keypoints, inputs.pairs, inputs.W,
                                          sizes=inputs.sizes, mapper=mapper_options(inputs, p, env.seed, refine),
                                          log=env.log.info)
    placed = np.flatnonzero(res.placed)
    if len(placed) == 0:
        env.log.warning("self-calibration registered no view; the intrinsics stay as the ingest gave them")
        return inputs.views.K, None, {"views": len(ids), "registered": 0}, None
    K, distortion = estimated_intrinsics(inputs, res)
    first = ids[placed[0]]
    log_refined(env, refine, inputs.views.K[first], K[first], distortion[first], f"{len(placed)}/{len(ids)} trainable views")
    return K, distortion, {"views": len(ids), "registered": int(len(placed)), "refine": list(refine),
               "K": K[first].tolist(), "distortion": distortion[first].tolist(),
               "principal_point_test": res.diagnostics["principal_point_test"],
               "radial_test": res.diagnostics["radial_test"],
               "mean_reproj_px": res.diagnostics["mean_reproj_px"], "seconds": res.diagnostics["seconds_total"]}, res


def matches_init(env: InitEnv, inputs: posefree.SceneInputs, anchors: list[int], p: Params, refine=()
                 ) -> pose_init.InitResult:
    """The `matches` initialisation of the anchors (and of the views that bridge them, whose poses
    are not kept): COLMAP on the front-end's matches (bundle adjustment refining the intrinsics
    ``refine``), then the gauge."""
    ids = init_views(anchors, inputs.W, np.flatnonzero(inputs.train_mask), p.bridge_min_matches)
    bridges = sorted(set(ids) - set(anchors))
    if bridges:
        env.log.info("the anchors' own matches link them weakly (weakest spanning link %g < %d matches): their "
                     "initialisation also uses views %s, which bridge them", mavos.bottleneck_weight(inputs.W, anchors),
                     p.bridge_min_matches, [inputs.names[v] for v in bridges])
    masks = None if inputs.views.masks is None else [inputs.views.masks[v] for v in ids]
    with io.native_output_to(env.log_path):  # COLMAP's own log goes to log.txt
        return pose_init.init_from_matches(ids, inputs.views.K, inputs.keypoints, inputs.pairs, inputs.W,
                                           sizes=inputs.sizes, mapper=mapper_options(inputs, p, env.seed, refine),
                                           gauge=gauge_options(p),
                                           masks=masks, log=env.log.info)


def init_views(anchors: list[int], W: np.ndarray, trainable, min_matches: int) -> list[int]:
    """The views whose matches initialise the anchors: the anchors alone when their own graph's
    weakest spanning link has at least ``min_matches`` verified matches; else the anchors and the
    trainable views on the maximum spanning tree of all trainable views that connects them
    (its smallest subtree holding every anchor reachable from the first)."""
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    if min_matches <= 0 or len(anchors) < 2 or mavos.bottleneck_weight(W, anchors) >= min_matches:
        return list(anchors)
    ids = np.union1d(np.asarray(trainable, int), anchors)
    tree = -minimum_spanning_tree(-W[np.ix_(ids, ids)]).toarray()  # the strongest links that span them
    tree = (tree + tree.T) > 0
    keep = np.isin(ids, anchors)
    degree = tree.sum(1)
    leaves = [i for i in range(len(ids)) if degree[i] == 1 and not keep[i]]
    while leaves:  # prune branches that lead to no anchor
        i = leaves.pop()
        degree[i] = 0
        for j in np.flatnonzero(tree[i]):
            tree[i, j] = tree[j, i] = False
            degree[j] -= 1
            if degree[j] == 1 and not keep[j]:
                leaves.append(j)
    first = int(np.flatnonzero(keep)[0])
    reached = breadth_first_order(tree, first, directed=False, return_predecessors=False)
    return sorted(set(int(ids[i]) for i in reached) | set(map(int, anchors)))


def perturbed(w2c: np.ndarray, p: Params, seed: int) -> np.ndarray:
    from manifoldneus.geometry import cameras

    distance = float(np.linalg.norm(cameras.camera_centers(w2c), axis=1).mean())
    return cameras.perturb_w2c(w2c, tuple(p.perturb_rot_deg), p.perturb_centre_frac * distance,
                               np.random.default_rng(seed))


def run(ctx) -> None:
    p: Params = ctx.params
    cfg = posefree.RoundConfig.from_sections(ctx.section, ctx.log_path)
    inputs = posefree.load_inputs(**{s: ctx.input(s) for s in posefree.INPUT_STAGES})
    rounds = inputs.schedule["round"]
    anchors = [int(v) for v in np.flatnonzero((rounds == 0) & inputs.train_mask)]
    if len(anchors) < 2:
        raise RuntimeError(f"only {len(anchors)} trainable anchor view(s); check schedule.anchor_percent and "
                           f"split.holdout_every")
    n = len(inputs.names)
    env = InitEnv(ctx.log, ctx.log_path, ctx.section("run").seed)
    # every round uses the K and lens distortion the initial poses belong to
    reference_dir = ctx.input("reference") if p.pose_init == "reference" else None
    w2c0, inputs, init_info, sfm_points = initial_poses(env, inputs, anchors, p, reference_dir, ctx.input("ingest"))
    if max(p.perturb_rot_deg, default=0.0) > 0 or p.perturb_centre_frac > 0:
        w2c0[anchors] = perturbed(w2c0[anchors], p, ctx.section("run").seed)
        init_info["perturbed"] = {"rot_deg": list(p.perturb_rot_deg), "centre_frac": p.perturb_centre_frac}
        ctx.log.info("anchors: initial poses perturbed by %s deg and %g of their distance (anchors.perturb_*)",
                     p.perturb_rot_deg, p.perturb_centre_frac)
    if not p.optimise_poses:  # poses held (sfm-all, neus-colmap): a view the SfM did not register has no pose to train on
        no_pose = set(init_info.get("unplaced", [])) | set(init_info.get("unregistered", []))
        if no_pose:
            ctx.log.warning("anchors: with poses held (anchors.optimise_poses = false) %s, which the initialisation "
                            "could not place, are left out instead", sorted(no_pose))
            anchors = [a for a in anchors if inputs.names[a] not in no_pose]
            if len(anchors) < 2:
                raise RuntimeError(f"the initialisation placed {len(anchors)} view(s); poses held, nothing to train on")
    placed = np.zeros(n, bool)
    placed[anchors] = True
    lens = {} if inputs.distortion is None else {"distortion": inputs.distortion}
    artifacts.save_initial_poses(ctx.out, {"w2c": w2c0, "placed": placed, "K": inputs.views.K, **lens,
                                           **{k: v.astype(np.float32) for k, v in sfm_points.items()}})
    ctx.log.info("anchors %s initialised by %s", [inputs.names[a] for a in anchors], init_info["method"])

    s_tilde = inputs.schedule["s_tilde_rounds"][0]
    ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
    rnd = posefree.Round(cfg, inputs, anchors, w2c0, s_tilde, iters=p.iters, poses=posefree.PoseLearning.of(p),
                         sfm_points=sfm_points)
    summary = rnd.run("anchors", ctx.checkpoint_dir / f"{artifacts.ANCHOR_ROUND}.pt", log=ctx.log, progress=ctx.progress)
    posefree.save_round(ctx.out / artifacts.ANCHOR_ROUND, rnd, placed, {
        "round": 0, "views": anchors, "names": [inputs.names[a] for a in anchors], "init": init_info,
        "train": summary, "history": rnd.trainer.history})
    ctx.metrics.update(n_anchors=len(anchors), init=init_info["method"], seconds=summary["seconds"],
                       final_loss=summary["final_loss"], rollbacks=summary["rollbacks"],
                       losses_on=sorted(k for k, v in summary["loss_status"].items() if v == "on"))
