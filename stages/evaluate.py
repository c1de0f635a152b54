"""evaluate: pose errors after every round (and of the initial poses), geometry, novel views.

- Poses: Sim3 (Umeyama on camera centres) alignment to GT, rotation / centre errors, PRE_r/PRE_t
  (:mod:`manifoldneus.geometry.pose_metrics`), for the initial anchor poses, the anchor round and every
  successor round, over the views optimised in that round.
- Geometry: Chamfer of the final mesh (mapped into the GT frame by the final Sim3) against the
  exact surface (synthetic scenes: the observed part of it), or else against the mesh of the
  GT-pose `reference_surface`, labelled so. Distances in scene units and in data units (mm).
  Beside it, the colour spread of the mesh (and of that reference mesh) across the views at the
  images' own size under the GT cameras (:mod:`manifoldneus.output.photo_consistency`): a check of
  where the surface lies that needs no masks and no reference.
- Novel views: held-out views rendered from the final model with their GT poses mapped into
  the model's frame through the inverse Sim3; PSNR/SSIM masked and unmasked; and again after
  test-time alignment (each held-out pose refined against the frozen field: `aligned_*`).
- Intrinsics: the camera the run started from and ended with (and its lens distortion), also for a
  scene without ground truth (a user's photos), where nothing else is scored.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from manifoldneus.data import artifacts, io
from manifoldneus.geometry import cameras, pose_metrics
from manifoldneus.output import evaluation, meshing, metrics, photo_consistency
from manifoldneus.config import holdout_mask, param


@dataclass
class Params:
    """Section `evaluate` of params.yaml."""

    chamfer_points: int = param(100000, "Points sampled on each surface for Chamfer", lo=1000)
    chamfer_max_dist: float = param(0.0, "Clip distances at this many scene units (0 = no clip)", lo=0.0)
    colour_spread_tolerance: float = param(0.005, "Colour spread: a surface point counts as seen by a view when it "
                                           "lies within this many scene units (plus two pixels' width) of the "
                                           "nearest surface along that view's ray (1.2 mm on DTU's scan24)", lo=0.0)


UPSTREAM = ("ingest", "ground_truth", "anchors", "successors", "surface", "mesh", "reference_surface")
SECTIONS = ("evaluate", "run.device", "split", "novel_views")
OUTPUTS = (artifacts.EVALUATION, artifacts.POSE_ERROR_PLOT)


def input_signature(scene, p) -> str:
    """LPIPS's weights (named by an environment variable) change the scores: their content counts."""
    return metrics.lpips_signature()


def _rounds(ctx) -> list[tuple[str, dict]]:
    """(label, poses) per row: the anchors' initial poses, then each round."""
    out = [("initial", artifacts.load_initial_poses(ctx.input("anchors")))]
    out.append(("anchors", artifacts.load_round(ctx.input("anchors") / artifacts.ANCHOR_ROUND)))
    succ = ctx.input("successors")
    for d in artifacts.successor_rounds(succ):
        out.append((d.name, artifacts.load_round(d)))
    return out


def placement_poses(rounds: list[tuple[str, dict]]) -> np.ndarray:
    """Every view at the pose it had when it was first placed (anchors: the initialisation; a
    successor: the pose its round started it from): what the rounds refine, view for view."""
    w2c = np.array(rounds[0][1]["w2c"])
    first = np.array(rounds[0][1]["placed"], bool)
    for _, r in rounds[1:]:
        new = r["placed"].astype(bool) & ~first
        w2c[new] = r["w2c_init"][new]
        first |= new
    return w2c


def plot_rounds(rows: list[dict], path, units: str) -> None:
    """Pose error after each round (mean and median over its views, against ground truth after a Sim3)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    x = [f"{r['label']}\n({r['n_views']} views)" for r in rows]
    for a, key, what in ((ax[0], "rot_err_deg", "rotation error (deg)"),
                         (ax[1], "center_err_units", f"camera centre error ({units})")):
        a.plot(x, [r["summary"][key]["mean"] for r in rows], "o-", label="mean")
        a.plot(x, [r["summary"][key]["median"] for r in rows], "s--", label="median")
        io.log_y(a)
        a.set_title(f"{what} after each round")
        a.set_xlabel("round")
        a.set_ylabel(what)
        a.legend()
    fig.tight_layout()
    io.save_figure(path, fig)


def intrinsics_report(ctx, rounds: list[tuple[str, dict]], K_gt: np.ndarray | None) -> dict:
    """The intrinsics the ingest started from and those the poses ended with (mean over the views
    the last round placed), and their error against the layout's own calibration where it has one."""
    ingest_K = artifacts.load_views_arrays(ctx.input("ingest"), ["K"])["K"]
    final = rounds[-1][1]
    placed = final["placed"].astype(bool)
    out = {"source": artifacts.load_views_meta(ctx.input("ingest")).get("intrinsics_source", "calibrated")}

    def describe(K):
        K = np.asarray(K)[placed]
        return {"focal_px": float(K[:, [0, 1], [0, 1]].mean()), "principal_point_px": K[:, :2, 2].mean(0).tolist()}

    out["start"], out["final"] = describe(ingest_K), describe(final["K"])
    if final.get("distortion") is not None:  # the lens distortion the self-calibration found and removed
        out["final"]["distortion"] = np.asarray(final["distortion"])[placed].mean(0).tolist()
    if K_gt is not None:
        out["ground_truth"] = describe(K_gt)
        for key in ("start", "final"):
            out[key]["focal_err_pct"] = 100 * abs(out[key]["focal_px"] / out["ground_truth"]["focal_px"] - 1)
    ctx.log.info("intrinsics (%s): focal %.1f px at the start, %.1f px final%s", out["source"],
                 out["start"]["focal_px"], out["final"]["focal_px"],
                 f" (ground truth {out['ground_truth']['focal_px']:.1f} px: {out['final']['focal_err_pct']:.2f} % off)"
                 if K_gt is not None else "")
    return out


def colour_spreads(mesh, ref_mesh, alignment: dict, gt_views, w2c_gt: np.ndarray, tolerance: float) -> dict:
    """The colour spread (:func:`manifoldneus.output.photo_consistency.colour_spread`) of the run's mesh, mapped
    into the GT frame by ``alignment``, and of ``ref_mesh`` (already there) when given."""
    grey = [photo_consistency.grey_levels(image[:h, :w]) for image, (h, w) in zip(gt_views.images, gt_views.view_sizes)]
    in_gt = mesh.copy()
    in_gt.apply_transform(cameras.sim3_matrix(alignment["s"], np.asarray(alignment["R"]), np.asarray(alignment["t"])))
    out = {"colour_spread": photo_consistency.colour_spread(in_gt, grey, gt_views.K, w2c_gt, depth_tolerance=tolerance)}
    if ref_mesh is not None:
        out["reference_colour_spread"] = photo_consistency.colour_spread(ref_mesh, grey, gt_views.K, w2c_gt,
                                                                         depth_tolerance=tolerance)
    return out


def run(ctx) -> None:
    p: Params = ctx.params
    gt_meta = artifacts.load_gt_meta(ctx.input("ground_truth"))
    names = artifacts.load_views_meta(ctx.input("ingest"))["names"]
    report: dict = {"label": ctx.scene}
    if not gt_meta["has_poses"]:
        ctx.log.info("no ground truth: nothing to score (the camera the run estimated is reported)")
        # the camera the run ended with is still worth saying: a user's photos are where it was estimated
        io.save_json(ctx.out / artifacts.EVALUATION,
                     {"has_ground_truth": False, "intrinsics": intrinsics_report(ctx, _rounds(ctx), None)})
        io.save_png(ctx.out / artifacts.POSE_ERROR_PLOT, np.zeros((8, 8, 3)))
        return
    gt = artifacts.load_ground_truth_poses(ctx.input("ground_truth"))
    units = gt_meta["units_per_scene_unit"]
    # --- poses per round
    rows = []
    final_res = None
    rounds = _rounds(ctx)
    for label, r in rounds:
        valid = r["placed"].astype(bool) & (r.get("optimised", r["placed"]).astype(bool))
        if valid.sum() < 3:  # a Sim3 needs 3 centres (e.g. K = 10 % of a sparse set)
            ctx.log.warning("%s: only %d views, too few to align and score", label, int(valid.sum()))
            rows.append({"label": label, "n_views": int(valid.sum()), "skipped": "fewer than 3 views: no Sim3"})
            continue
        res = pose_metrics.evaluate_poses(r["w2c"], gt["w2c"], valid=valid, units_scale=units)
        row = {"label": label, "summary": res["summary"], "n_views": res["n_valid"],
               "per_view": pose_metrics.json_summary(res, names)["per_view"]}
        if "w2c_init" in r:  # the same views at the poses this round started from
            row["start_summary"] = pose_metrics.evaluate_poses(r["w2c_init"], gt["w2c"], valid=valid,
                                                               units_scale=units)["summary"]
        if "info" in r:
            row["guard"] = r["info"].get("train", {}).get("guard")
        rows.append(row)
        mean = {k: res["summary"][k]["mean"] for k in ("rot_err_deg", "center_err_units")}
        # None: no finite error (e.g. identity init: every centre alike, no Sim3 scale)
        mean = {k: "n/a" if v is None else f"{v:.3f}" for k, v in mean.items()}
        ctx.log.info("%-9s %2d views: rotation %s deg, centre %s %s (mean)", label, res["n_valid"],
                     mean["rot_err_deg"], mean["center_err_units"], gt_meta["units"])
        final_res = res
    report["poses"] = rows
    report["intrinsics"] = intrinsics_report(ctx, rounds, gt.get("K"))
    if final_res is not None:  # the final views at their placement poses: what the rounds started from
        report["placement"] = pose_metrics.evaluate_poses(placement_poses(rounds), gt["w2c"], valid=final_res["valid"],
                                                          units_scale=units)["summary"]
        ctx.metrics["placement_rot_err_deg_mean"] = report["placement"]["rot_err_deg"]["mean"]
        ctx.log.info("placement: the final views at their first poses: rotation %.3f deg (mean)",
                     report["placement"]["rot_err_deg"]["mean"])
    plot_rounds([r for r in rows if "summary" in r], ctx.out / artifacts.POSE_ERROR_PLOT, gt_meta["units"])
    if final_res is None or "summary" not in rows[-1]:
        ctx.log.warning("the final round could not be scored: no geometry or novel-view evaluation")
        io.save_json(ctx.out / artifacts.EVALUATION, report)
        return
    pose_metrics.plot_cameras(final_res["w2c_aligned"], gt["w2c"], ctx.out / artifacts.CAMERAS_PLOT, valid=final_res["valid"],
                              held_out=holdout_mask(len(names), ctx.section("split")),
                              title=f"{ctx.scene}: final poses (Sim3-aligned) vs GT")
    # --- geometry

    mesh = meshing.load_mesh(ctx.input("mesh") / artifacts.MESH)
    al = final_res["alignment"]
    pred = metrics.sample_surface(mesh, p.chamfer_points) if len(mesh.faces) else np.zeros((0, 3))
    pred = al["s"] * pred @ np.asarray(al["R"]).T + np.asarray(al["t"])
    ref_label, ref_pts, ref_mesh = None, None, None
    gt_views = artifacts.load_views(ctx.input("ingest"), K=gt.get("K"))  # the images' own size, the GT cameras
    if gt_meta.get("has_surface"):
        from manifoldneus.data import synthetic

        surf = gt["surface_points"]
        h, w = gt_views.images.shape[1:3]
        ref_pts = surf[synthetic.points_visible(surf, gt_views.K, gt["w2c"], h, w)]
        ref_label = "exact surface (observed part)"
        diag = float(np.linalg.norm(np.subtract(*synthetic.bounding_box()[::-1])))
    else:
        ref_meta = artifacts.load_reference_surface_meta(ctx.input("reference_surface"))
        if ref_meta.get("trained"):
            ref_mesh = meshing.load_mesh(ctx.input("reference_surface") / artifacts.MESH)
            ref_pts = metrics.sample_surface(ref_mesh, p.chamfer_points)
            ref_label = "mesh of the GT-pose reference_surface (not DTU's official point cloud)"
            diag = float(np.linalg.norm(ref_pts.max(0) - ref_pts.min(0)))
    if ref_pts is not None:
        ch = metrics.chamfer(pred, ref_pts, p.chamfer_max_dist or None)
        ch_units = {f"{k}_units": v * units for k, v in ch.items()}
        report["geometry"] = {"reference": ref_label, **ch, **ch_units, "units": gt_meta["units"],
                              "chamfer_pct_of_bbox_diagonal": 100 * ch["chamfer"] / diag}
        report["geometry"].update(colour_spreads(mesh, ref_mesh, al, gt_views, gt["w2c"], p.colour_spread_tolerance))
    # --- novel views of held-out views
    held = np.flatnonzero(holdout_mask(len(names), ctx.section("split")))
    if len(held):
        surface = evaluation.load_surface_field(ctx.input("surface"), ctx.input("ingest"), ctx.section("run").device)
        views = surface.views
        # the ground truth in the rounds' frame (the Sim3 of the final poses), then in the field's
        test_w2c = cameras.transform_w2c(evaluation.gt_in_model_frame(al, gt["w2c"]),
                                         *cameras.sim3_from_matrix(surface.field_from_model))
        if views.masks is None and "masks" in gt:  # scored on the object too, as a masked run is
            views = dataclasses.replace(views, masks=gt["masks"])
        report["novel_views"] = evaluation.novel_views(surface.trainer, views, held, test_w2c, ctx.out / "novel_views",
                                                       ctx.progress, align=ctx.section("novel_views"))
    io.save_json(ctx.out / artifacts.EVALUATION, report)
    fin = rows[-1]["summary"]
    ctx.metrics.update(
        rot_err_deg_mean=fin["rot_err_deg"]["mean"], center_err_units_mean=fin["center_err_units"]["mean"],
        pre_r_deg_mean=fin["pre_r_deg"]["mean"], pre_t_deg_mean=fin["pre_t_deg"]["mean"],
        units=gt_meta["units"])
    for row in rows:
        if "summary" in row:
            ctx.metrics[f"{row['label']}_rot_err_deg_mean"] = row["summary"]["rot_err_deg"]["mean"]
    ctx.metrics["focal_px"] = report["intrinsics"]["final"]["focal_px"]
    if "focal_err_pct" in report["intrinsics"]["final"]:
        ctx.metrics["focal_err_pct"] = report["intrinsics"]["final"]["focal_err_pct"]
    if "geometry" in report:
        ctx.metrics.update(chamfer_units=report["geometry"]["chamfer_units"],
                           chamfer_pct_bbox=report["geometry"]["chamfer_pct_of_bbox_diagonal"])
    if "novel_views" in report:
        ctx.metrics.update({f"nvs_{k}": v for k, v in report["novel_views"]["summary"].items() if isinstance(v, float)})
