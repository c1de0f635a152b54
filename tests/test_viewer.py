"""The viewer page (manifoldneus/output/viewer.py, `pipeline.py view`): its geometry helpers, its data
against the tiny run's artifacts, and the page rendered in headless Chromium."""
import html
import json
import re
from pathlib import Path

import numpy as np
import pytest

import runner
import pipeline
from manifoldneus.data import artifacts, io
from manifoldneus.geometry import cameras
from manifoldneus.output import viewer


def test_decimate_keeps_the_surface_within_a_cell_and_averages_colours():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces, radius 1
    colours = np.where(sphere.vertices[:, :1] > 0, [[255, 0, 0]], [[0, 0, 255]]).astype(np.uint8)
    v, f, c = viewer.decimate(np.asarray(sphere.vertices), np.asarray(sphere.faces), colours, 2000)
    assert 500 < len(f) <= 2000 and f.max() < len(v)
    radius = np.linalg.norm(v[np.unique(f)], axis=1)
    assert np.abs(radius - 1).max() < 0.1
    # a vertex far from the x = 0 border keeps its side's colour
    assert (c[v[:, 0] > 0.2] == [255, 0, 0]).all() and (c[v[:, 0] < -0.2] == [0, 0, 255]).all()
    same = viewer.decimate(np.asarray(sphere.vertices), np.asarray(sphere.faces), colours, 10**6)
    assert same[1] is sphere.faces or np.array_equal(same[1], sphere.faces)


def test_frustum_corners_project_onto_the_image_corners():
    K = np.array([[300.0, 0, 100.0], [0, 320.0, 60.0], [0, 0, 1]])
    w2c = cameras.look_at_w2c(np.array([2.0, -1.0, 0.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    pts = viewer.frustum_points(K[None], w2c[None], 200, 120, depth=0.3)[0]  # [5,3]
    np.testing.assert_allclose(pts[0], cameras.camera_centers(w2c), atol=1e-12)
    in_camera = pts[1:] @ w2c[:3, :3].T + w2c[:3, 3]
    np.testing.assert_allclose(in_camera[:, 2], 0.3, atol=1e-12)
    np.testing.assert_allclose(cameras.project_points(K, in_camera), [[0, 0], [200, 0], [200, 120], [0, 120]],
                               atol=1e-9)


def test_view_of_a_scene_without_a_run_says_what_to_run(tmp_path, capsys):
    assert pipeline.main(["view", "--scene", "synthetic", "--artifacts", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "has no exported result to view" in err and "run: python pipeline.py run --scene synthetic" in err


def page_data(path):
    text = path.read_text()
    return json.loads(re.search(r'<script type="application/json" id="scene-data">(.*?)</script>', text, re.S)
                      .group(1)), text


@pytest.fixture(scope="module")
def page(tiny_run, tmp_path_factory):
    """The tiny run's page, and the run's own numbers it must show (from the versions it was built from)."""
    artifacts_dir, _ = tiny_run
    path = tmp_path_factory.mktemp("viewer") / "viewer.html"
    assert pipeline.main(["view", "--scene", "synthetic", "--artifacts", str(artifacts_dir), "--out", str(path)]) == 0
    versions = runner.Store(artifacts_dir, "synthetic").lineage("export")
    final = artifacts.load_round(versions["successors"] / "final")
    schedule = io.load_json(versions["schedule"] / "schedule.json")
    run = {"optimised": int((final["placed"] & final["optimised"]).sum()), "held_out": len(schedule["held_out_views"]),
           "views": len(schedule["views"]), "rounds": 2 + len(list(versions["successors"].glob("round_*")))}
    return path, run


def test_the_page_holds_the_run_and_needs_no_network(page):
    path, run = page
    data, text = page_data(path)
    assert data["counts"] == {"views": run["views"], "optimised": run["optimised"], "held_out": run["held_out"],
                              "held_out_drawn": run["held_out"]}
    assert len(data["rounds"]) == run["rounds"] and data["rounds"][-1]["n_posed"] == run["optimised"]
    assert [r["label"] for r in data["rounds"][:2]] == ["initial", "anchors"]
    assert {c["role"] for c in data["cameras"]} >= {"anchor", "round1", "held out"}
    # a GT camera and an error for every camera of the final round; held-out views drawn at their GT pose
    final = data["rounds"][-1]
    posed = [i for i, f in enumerate(final["frusta"]) if f is not None]
    assert all(final["errors"][i] is not None and final["errors"][i][0] < 5.0 for i in posed)
    assert all(data["gt"]["frusta"][c["view"]] for c in data["cameras"] if c["role"] == "held out")
    assert data["mesh"]["n_faces"] > 0 and data["reference"]["n_points"] > 0
    # offline: no script or stylesheet from anywhere, three.js inlined with its licence
    assert not re.search(r"<script[^>]+src=|<link[^>]+href=|https?://(?!www\.w3\.org)", text.split("<details")[0])
    assert '"three":"data:text/javascript;base64,' in text.replace(" ", "") and "MIT License" in text


def test_decimated_page_stays_small(tiny_run, tmp_path):
    artifacts_dir, _ = tiny_run
    path, held = runner.view("synthetic", artifacts_dir, out=tmp_path / "small.html", max_faces=1000)
    data, _ = page_data(path)
    assert held["faces"] == data["mesh"]["n_faces"] <= 1000 < held["faces_full"]


def test_a_write_that_fails_midway_leaves_the_earlier_page(tiny_run, tmp_path, monkeypatch):
    """A full disk while the page is written: the good page written before stays whole, and nothing
    half-written is left beside it."""
    import errno

    artifacts_dir, _ = tiny_run
    path, _ = runner.view("synthetic", artifacts_dir, out=tmp_path / "v.html", max_faces=1000)
    before = path.read_bytes()
    real = Path.write_text

    def full_disk(self, text, *a, **k):
        real(self, text[: len(text) // 2])
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_text", full_disk)
    with pytest.raises(OSError):
        runner.view("synthetic", artifacts_dir, out=path, max_faces=1000)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["v.html"]


def test_the_page_renders_in_headless_chromium(page, tmp_path):
    """The run's page, its photos named like the template's placeholders and like HTML (see below),
    in a real browser: ready, every camera drawn, the mesh in the middle of the picture."""
    if viewer.find_browser() is None:
        pytest.skip("no Chromium on this machine (bash .ci/run installs the Debian package chromium)")
    _, run = page
    path = hostile_page(page[0], tmp_path)
    shown = viewer.render_in_browser(path, tmp_path / "viewer.png", size=(1000, 700))
    attrs = shown["attributes"]
    assert "errors" not in attrs, attrs["errors"]
    assert [m for m in shown["console"] if re.search(r"error|uncaught|warning", m, re.I)] == []
    assert attrs["viewer-state"] == "ready"
    assert int(attrs["cameras-drawn"]) == run["optimised"] and int(attrs["held-out-drawn"]) == run["held_out"]
    # the mesh is drawn in the middle of what the panel (about 300 px) leaves free (cameras are thin lines)
    drawn = drawn_fraction(tmp_path / "viewer.png", (0.4, 0.6, 0.58, 0.74))
    assert drawn > 0.5, f"only {drawn:.0%} of the free area's centre is drawn"


def drawn_fraction(png, box=(0.0, 1.0, 0.0, 1.0)) -> float:
    """Fraction of the picture (rows y0-y1, columns x0-x1, as fractions) not background."""
    from PIL import Image

    image = np.asarray(Image.open(png).convert("RGB")).astype(int)
    h, w = image.shape[:2]
    y0, y1, x0, x1 = box
    part = image[int(y0 * h):int(y1 * h), int(x0 * w):int(x1 * w)]
    return float((np.abs(part - np.array([0x1E, 0x21, 0x27])).max(-1) > 16).mean())


def test_fit_to_object_fills_the_view_beside_the_panel(page, tmp_path):
    """'fit object' (button, key f, or a link ending #view=object) frames the mesh in the part of the
    window the panel leaves free: the mesh covers far more of the picture than the reset view, whose
    every camera is in view, and the panel's side stays background."""
    if viewer.find_browser() is None:
        pytest.skip("no Chromium on this machine (bash .ci/run installs the Debian package chromium)")
    path, _ = page
    shown = {}
    for view, fragment in (("all", ""), ("object", "#view=object")):
        shown[view] = viewer.render_in_browser(path, tmp_path / f"{view}.png", size=(1000, 700), fragment=fragment)
        assert shown[view]["attributes"]["view"] == view and "errors" not in shown[view]["attributes"]
    right = (0.1, 0.9, 0.35, 0.95)  # the free area, right of the 290-px panel
    assert drawn_fraction(tmp_path / "object.png", right) > 2 * drawn_fraction(tmp_path / "all.png", right)
    assert 'id="fit-object"' in shown["object"]["dom"] and 'id="reset-view"' in shown["object"]["dom"]


def test_without_webgl_the_page_says_so(page, tmp_path):
    if viewer.find_browser() is None:
        pytest.skip("no Chromium on this machine (bash .ci/run installs the Debian package chromium)")
    shown = viewer.render_in_browser(page[0], tmp_path / "none.png", size=(800, 500), webgl=False)
    assert shown["attributes"]["viewer-state"] == "no-webgl"
    message = re.search(r'<div id="no-webgl"([^>]*)>', shown["dom"])
    assert message and "hidden" not in message.group(1) and "hardware acceleration" in shown["dom"]
    assert re.search(r'<div id="panel"[^>]*hidden', shown["dom"])


HOSTILE = ["{{APP}}", "<!--<script>", "{{IMPORTMAP}}", "</script><b>", "a&b \"q\""]
HOSTILE_TITLE = "{{IMPORTMAP}} <!--<script> {{DATA}}"


def hostile_page(path, tmp_path):
    """The page of ``path`` rebuilt with its cameras named from HOSTILE and HOSTILE_TITLE as title."""
    data, _ = page_data(path)
    for i, camera in enumerate(data["cameras"]):
        camera["name"] = HOSTILE[i % len(HOSTILE)]
    out = tmp_path / "hostile.html"
    out.write_text(viewer.build_page(data, HOSTILE_TITLE))
    return out


def test_names_that_look_like_the_template_or_html_stay_data(page, tmp_path):
    """Photos named like the template's placeholders or like HTML leave the page whole: filled in
    one pass, the JSON without '<' (the browser test renders this page)."""
    hostile = hostile_page(page[0], tmp_path)
    text = hostile.read_text()
    app = (viewer.ASSETS / "viewer.js").read_text()
    assert text.count(app) == 1 and text.count("<script type=\"importmap\">{\"imports\"") == 1
    data, _ = page_data(hostile)
    assert [c["name"] for c in data["cameras"]][:len(HOSTILE)] == HOSTILE
    assert f"<title>{html.escape(HOSTILE_TITLE)}</title>" in text
