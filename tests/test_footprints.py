"""Image footprints (footprints.csv) against closed forms: a flat floor seen from above, a
tilted plane (a trapezoid), a floor covering half the image, a step (a depth edge), and the
same scene moved by a similarity (issue #20)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from sfm_laserscale.footprints import (
    FootprintOptions,
    FootprintView,
    footprint_summary,
    footprints,
)
from sfm_laserscale.geometry import rotmat_from_qvec
from sfm_laserscale.io.footprints_csv import FOOTPRINT_COLUMNS, read_footprints_csv
from sfm_laserscale.io.models import load_model
from sfm_laserscale.model import Camera, Pose

W, H, FX, FY = 640, 480, 500.0, 520.0
CAM = Camera(1, "PINHOLE", W, H, np.array([FX, FY, W / 2, H / 2]))
LOOK_DOWN = Pose(np.eye(3), np.zeros(3))  # camera frame = world frame: the floor is z = D


def plane(corners: list[list[float]], n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A planar quad (corners in order) as an n × n grid of vertices, 2(n-1)² triangles."""
    c = np.asarray(corners, dtype=np.float64)
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    u, v = u.ravel()[:, None], v.ravel()[:, None]
    verts = (1 - u) * (1 - v) * c[0] + u * (1 - v) * c[1] + u * v * c[2] + (1 - u) * v * c[3]
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    cc, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    tris = np.vstack([np.column_stack([a, b, cc]), np.column_stack([a, cc, d])]).astype(np.int32)
    return verts, tris


def floor(depth: float, half: float = 100.0,
          x_from: float = -100.0) -> tuple[np.ndarray, np.ndarray]:
    return plane([[x_from, -half, depth], [half, -half, depth], [half, half, depth],
                  [x_from, half, depth]])


def one(view_pose: Pose, mesh: tuple[np.ndarray, np.ndarray], **opt: float):  # type: ignore[no-untyped-def]
    (fp,) = footprints([FootprintView("a.jpg", "laser", CAM, view_pose)], *mesh,
                       FootprintOptions(**opt))  # type: ignore[arg-type]
    return fp


@pytest.mark.parametrize("depth", [1.0, 3.7])
def test_flat_floor_from_above(depth: float) -> None:
    fp = one(LOOK_DOWN, floor(depth))
    assert fp.area == pytest.approx(W * H * depth ** 2 / (FX * FY), rel=1e-9)
    assert fp.gsd_centre == pytest.approx(depth / math.sqrt(FX * FY), rel=1e-9)
    assert fp.on_mesh_fraction == 1.0 and fp.reason is None
    assert fp.grid == (64, 48)
    # every cell covers the same area on a facing plane
    assert fp.gsd_median == pytest.approx(depth / math.sqrt(FX * FY), rel=1e-9)
    corner = math.hypot(1, math.hypot(W / 2 / FX, H / 2 / FY))
    assert depth < fp.distance < depth * corner


def trapezoid_area(depth: float, tilt: float) -> float:
    """Closed form: the footprint of the camera on the plane z = D + y tan(tilt) (a rotation
    about x): the image rows v = const map to segments parallel to x, so it is a trapezoid."""
    def t(v: float) -> float:
        return depth / (1 - v * math.tan(tilt))
    v0, v1 = (0 - H / 2) / FY, (H - H / 2) / FY
    w0, w1 = W / FX * t(v0), W / FX * t(v1)
    height = math.dist((v0 * t(v0), t(v0)), (v1 * t(v1), t(v1)))
    return 0.5 * (w0 + w1) * height


@pytest.mark.parametrize("tilt_deg", [15.0, -30.0, 50.0])
def test_tilted_plane_is_a_trapezoid(tilt_deg: float) -> None:
    depth, tilt, big = 2.0, math.radians(tilt_deg), 100.0
    z = [depth + y * math.tan(tilt) for y in (-big, big)]
    mesh = plane([[-big, -big, z[0]], [big, -big, z[0]], [big, big, z[1]], [-big, big, z[1]]])
    fp = one(LOOK_DOWN, mesh)
    assert fp.area == pytest.approx(trapezoid_area(depth, tilt), rel=1e-9)
    assert fp.area > W * H * depth ** 2 / (FX * FY)  # a tilted floor shows more of itself
    # at the centre the ray meets the plane at range D, at incidence = tilt
    assert fp.gsd_centre == pytest.approx(depth / math.sqrt(FX * FY * math.cos(tilt)), rel=1e-4)
    assert fp.on_mesh_fraction == 1.0


def test_floor_under_half_the_image() -> None:
    depth = 2.0
    fp = one(LOOK_DOWN, floor(depth, x_from=0.0))  # the floor ends under the image's centre
    assert fp.on_mesh_fraction == pytest.approx(0.5)
    assert fp.area == pytest.approx(0.5 * W * H * depth ** 2 / (FX * FY), rel=1e-9)


def test_depth_edge_cells_are_left_out() -> None:
    left = plane([[-100, -100, 2.0], [0, -100, 2.0], [0, 100, 2.0], [-100, 100, 2.0]])
    right = plane([[0, -100, 6.0], [100, -100, 6.0], [100, 100, 6.0], [0, 100, 6.0]])
    verts = np.vstack([left[0], right[0]])
    tris = np.vstack([left[1], right[1] + len(left[0])])
    fp = one(LOOK_DOWN, (verts, tris))
    cols = 64
    # the column of cells across the step spans both floors: not counted
    assert fp.on_mesh_fraction == pytest.approx((cols - 1) / cols)
    half = 0.5 * W * H / (FX * FY)
    expected = half * 2.0 ** 2 + half * 6.0 ** 2  # both halves, minus one column of cells
    column = (W / cols) * H / (FX * FY)
    assert expected - column * 6.0 ** 2 <= fp.area <= expected


def test_similarity_moves_area_by_scale_squared() -> None:
    """The same scene in another model frame (rotated, moved, 2.5× larger): the area in model
    units grows by 2.5², and the metric area at the matching scale is unchanged."""
    depth, k = 2.0, 2.5
    R = rotmat_from_qvec(np.array([0.9, 0.2, -0.3, 0.25]) / np.linalg.norm([0.9, 0.2, -0.3, 0.25]))
    t = np.array([10.0, -4.0, 3.0])
    verts, tris = plane([[-50, -40, depth], [60, -40, depth + 5], [60, 45, depth + 5],
                         [-50, 45, depth]])
    base = one(LOOK_DOWN, (verts, tris))
    moved_verts = k * verts @ R.T + t  # world' = k R world + t; the camera moves with it:
    moved = one(Pose(R.T.copy(), -R.T @ t), (moved_verts, tris))  # centre t, axes R
    assert moved.area == pytest.approx(k ** 2 * base.area, rel=1e-6)
    assert moved.metric(1 / k)["area_m2"] == pytest.approx(base.area, rel=1e-6)
    assert moved.metric(1 / k)["gsd_mm_centre"] == pytest.approx(base.gsd_centre * 1e3, rel=1e-6)
    assert moved.metric(1 / k)["distance_m"] == pytest.approx(base.distance, rel=1e-6)


def test_views_without_pose_and_off_mesh_have_reasons() -> None:
    views = [FootprintView("a.jpg", "laser", CAM, None, reason="not registered: only 3 inliers"),
             FootprintView("b.jpg", "model", CAM, LOOK_DOWN),
             FootprintView("c.jpg", "model", CAM, Pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3)))]
    a, b, c = footprints(views, *floor(2.0))
    assert a.reason == "not registered: only 3 inliers" and math.isnan(a.area)
    assert b.reason is None and b.area > 0
    assert c.reason is not None and c.area == 0.0 and c.on_mesh_fraction == 0.0  # looks up
    row = a.metric(0.5)
    assert row["image"] == "a.jpg" and row["area_m2"] is None
    summary = footprint_summary((a, b, c), 0.5)
    assert summary["n_images"] == 3 and summary["n_laser_images"] == 1
    assert summary["n_model_images"] == 2 and summary["n_on_mesh"] == 1
    assert summary["area_m2"]["median"] == pytest.approx(b.area * 0.25)
    assert sum(summary["histogram_area_m2"]["model"]) == 1  # c is off the mesh
    assert sum(summary["histogram_area_m2"]["laser"]) == 0


def test_large_meshes_are_cast_in_groups_with_the_same_result() -> None:
    mesh = plane([[-100, -100, 2.0], [100, -100, 3.0], [100, 100, 2.5], [-100, 100, 2.0]], n=40)
    views = [FootprintView(f"{i}.jpg", "model", CAM,
                           Pose(np.eye(3), np.array([-3.0 * i, 0.5 * i, 0.0])))
             for i in range(6)]
    whole = footprints(views, *mesh)
    grouped = footprints(views, *mesh, FootprintOptions(max_crop_triangles=500))
    for a, b in zip(whole, grouped, strict=True):
        assert b.area == pytest.approx(a.area, rel=1e-12) and a.area > 0


# ---------------------------------------------------------------------------- in a scale run

def test_scale_writes_footprints_of_every_image(small_scale_run: Any, small_dataset: Any) -> None:
    """footprints.csv: a row per laser image and per model image, the metric values of the
    run's footprints at its scale, and report.json's distribution of them."""
    out, s = small_scale_run.out_dir, small_scale_run.scale.value
    rows = read_footprints_csv(out / "footprints.csv")
    laser = sorted(p.name for p in small_dataset.laser_images_dir.iterdir())
    model = sorted(im.name for im in load_model(small_dataset.model_dir).images.values())
    assert [r["image"] for r in rows] == laser + model
    assert list(rows[0]) == list(FOOTPRINT_COLUMNS)
    for row, fp in zip(rows, small_scale_run.footprints, strict=True):
        assert row["area_m2"] == pytest.approx(fp.area * s ** 2, rel=1e-5)
        assert row["gsd_mm_median"] == pytest.approx(fp.gsd_median * s * 1e3, rel=1e-5)
        assert 0 < row["footprint_on_mesh_fraction"] <= 1
    # a facing view: area ≈ (W·H) (D/f)² with the image's own range and GSD
    for row in rows:
        assert row["area_m2"] == pytest.approx(
            row["gsd_mm_median"] ** 2 * 1e-6 * 640 * 480 * row["footprint_on_mesh_fraction"],
            rel=0.35)
    report = small_scale_run.report
    block = report["footprints"]
    assert block["n_images"] == len(rows) and block["n_laser_images"] == len(laser)
    assert block["area_m2"]["median"] == pytest.approx(
        float(np.median([r["area_m2"] for r in rows])), rel=1e-5)  # the CSV's 6 digits
    # the laser images' range agrees with the range of their spots' hits
    dist = {im["name"]: im.get("distance_m") for im in report["images"]}
    for row in rows[:len(laser)]:
        if dist[row["image"]] is not None:
            assert row["distance_m"] == pytest.approx(dist[row["image"]], rel=0.25)
    assert 'id="footprints"' in (out / "report.html").read_text()


def test_the_benchmark_script_runs(capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from script_loader import load_script

    bench = load_script("bench_footprints")
    monkeypatch.setattr("sys.argv", ["bench_footprints", "--triangles", "5000", "--images",
                                     "4", "--repeat", "1", "--width", "320", "--height", "240"])
    bench.main()
    out = capsys.readouterr().out
    assert "whole mesh" in out and "cropped groups" in out and "(4 on the mesh" in out
