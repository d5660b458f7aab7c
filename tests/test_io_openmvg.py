"""OpenMVG input/output: sfm_data.json, SIFT regions, rescaled sfm_data.json.

Real fixture: ../shared/fixtures/maupertuis_openmvg (never modified: files are copied to
tmp_path before anything could write). Measured numbers are printed (``-s`` to see them).
"""

from __future__ import annotations

import copy
import hashlib
import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sfm_laserscale.errors import InputError
from sfm_laserscale.geometry import rotation_angle_deg
from sfm_laserscale.io import openmvg
from sfm_laserscale.io.colmap import model_without_images
from sfm_laserscale.io.images import read_rgb
from sfm_laserscale.io.models import load_model
from sfm_laserscale.io.openmvg import (
    VLFEAT_TO_COLMAP,
    find_openmvg_regions_dir,
    openmvg_model_features,
    openmvg_sift_to_colmap,
    parse_openmvg_sfm_data,
    read_openmvg_regions,
    read_openmvg_sfm_data,
    write_scaled_openmvg_sfm_data,
)
from sfm_laserscale.model import (
    INVALID_POINT3D_ID,
    Camera,
    ImageFeatures,
    ObservationFeatures,
    SparseModel,
)
from sfm_laserscale.registration.features import load_model_features
from sfm_laserscale.registration.index import build_descriptor_index
from sfm_laserscale.registration.options import RegistrationOptions, SiftOptions, TieOptions
from sfm_laserscale.registration.pose import register_image
from sfm_laserscale.registration.sift import extract_sift

F64 = NDArray[np.float64]
FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures"
OMVG = FIXTURES / "maupertuis_openmvg"
SFM = OMVG / "sfm_data.json"
HELD_OUT = "MaupertuisTest_04.jpg"
NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?")


# --------------------------------------------------------------------------- helpers


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _observation_errors(model: SparseModel, camera_of: dict[int, Camera] | None = None) -> F64:
    """Distance between each observation with a 3D point and its reprojection (pixels)."""
    errs = []
    for im in model.images.values():
        ok = im.point3D_ids != INVALID_POINT3D_ID
        xyz = model.points_xyz[[model.point_index[int(p)] for p in im.point3D_ids[ok]]]
        cam = (camera_of or model.cameras)[im.camera_id]
        errs.append(np.linalg.norm(cam.project(im.cam_from_world.transform(xyz)) - im.xy_px[ok],
                                   axis=1))
    return np.concatenate(errs)


def _shift_pp(cam: Camera, dxy: float) -> Camera:
    """The same camera with its principal point moved by dxy (pixels, both axes)."""
    params = cam.params.copy()
    i = 1 if cam.model in ("SIMPLE_RADIAL", "SIMPLE_PINHOLE") else 2
    params[i:i + 2] += dxy
    return Camera(cam.camera_id, cam.model, cam.width, cam.height, params)


@pytest.fixture(scope="module")
def model() -> SparseModel:
    return read_openmvg_sfm_data(SFM)


@pytest.fixture(scope="module")
def regions(model: SparseModel) -> dict[str, ImageFeatures]:
    feats = openmvg_model_features(model, SFM, OMVG / "matches")
    assert all(isinstance(f, ImageFeatures) for f in feats.values())
    return feats  # type: ignore[return-value]


@pytest.fixture(scope="module")
def query() -> ImageFeatures:
    """Fresh pycolmap SIFT of the held-out JPEG (COLMAP pixels, COLMAP bin order)."""
    return extract_sift(read_rgb(OMVG / "images" / HELD_OUT), SiftOptions())


# --------------------------------------------------------------------------- real fixture


def test_fixture_loads_views_intrinsics_poses_and_structure(model: SparseModel) -> None:
    doc = json.loads(SFM.read_text())
    assert model.source_format == "openmvg"
    assert len(model.images) == 4 and len(model.cameras) == 1 and len(model.points_xyz) == 365
    cam = model.cameras[0]
    intr = doc["intrinsics"][0]["value"]["ptr_wrapper"]["data"]
    k1, k2, k3 = intr["disto_k3"]
    f, (cx, cy) = intr["focal_length"], intr["principal_point"]
    assert cam.model == "FULL_OPENCV" and (cam.width, cam.height) == (1600, 1200)
    np.testing.assert_array_equal(cam.params, [f, f, cx + 0.5, cy + 0.5, k1, k2, 0, 0, k3, 0, 0, 0])
    for entry in doc["views"]:
        view = entry["value"]["ptr_wrapper"]["data"]
        im = model.images[view["id_view"]]
        assert im.name == view["filename"] and im.camera_id == view["id_intrinsic"] == 0
        pose = next(e["value"] for e in doc["extrinsics"] if e["key"] == view["id_pose"])
        np.testing.assert_allclose(im.cam_from_world.R, pose["rotation"], rtol=0, atol=0)
        np.testing.assert_allclose(im.cam_from_world.center, pose["center"], atol=1e-15)
        # keypoint i of the regions = observation i (every keypoint of the .feat file)
        feat_file = OMVG / "matches" / (Path(im.name).stem + ".feat")
        n_feat = len(feat_file.read_text().splitlines())
        assert len(im.xy_px) == len(im.point3D_ids) == n_feat
    n_obs = sum(len(lm["value"]["observations"]) for lm in doc["structure"])
    assert sum(int((im.point3D_ids != INVALID_POINT3D_ID).sum())
               for im in model.images.values()) == n_obs == 1228
    lm = doc["structure"][0]["value"]
    np.testing.assert_array_equal(model.points_xyz[model.point_index[0]], lm["X"])
    for ob in lm["observations"]:  # landmark x (+0.5) is keypoint id_feat of the view
        im = model.images[ob["key"]]
        assert im.point3D_ids[ob["value"]["id_feat"]] == 0
        np.testing.assert_allclose(im.xy_px[ob["value"]["id_feat"]], np.add(ob["value"]["x"], 0.5),
                                   atol=1e-3)


def test_fixture_reprojection_and_the_half_pixel_shift(model: SparseModel) -> None:
    err = _observation_errors(model)
    # The same observations against cameras whose principal point was not shifted: what a
    # reader gets when it converts the keypoints but forgets the intrinsics (or vice versa).
    unshifted = {k: _shift_pp(c, -0.5) for k, c in model.cameras.items()}
    err_no_shift = _observation_errors(model, unshifted)
    print(f"\nreprojection of {len(err)} observations: mean {err.mean():.3f} px, median "
          f"{np.median(err):.3f} px; principal point without +0.5: mean {err_no_shift.mean():.3f}"
          f" px, median {np.median(err_no_shift):.3f} px")
    assert err.mean() < 1.0 and np.median(err) < 0.5
    assert err_no_shift.mean() > err.mean() + 0.25


def test_regions_pixel_convention_and_descriptor_bin_order(
        regions: dict[str, ImageFeatures], query: ImageFeatures) -> None:
    """OpenMVG keypoints +0.5 px land on pycolmap's; reordered descriptors match pycolmap's."""
    ours = regions[HELD_OUT]
    stored = ours.descriptors[:, np.argsort(VLFEAT_TO_COLMAP)]  # back to the .desc order
    np.testing.assert_array_equal(
        stored, np.fromfile(OMVG / "matches" / "MaupertuisTest_04.desc", np.uint8)[8:].reshape(-1,
                                                                                                 128))
    tree = cKDTree(query.xy_px)
    dist, nn = tree.query(ours.xy_px)
    close = dist < 1.0
    offset = np.median(query.xy_px[nn[close]] - ours.xy_px[close], axis=0)
    assert close.mean() > 0.8 and np.all(np.abs(offset) < 0.05)  # raw .feat: +0.5 off
    groups = tree.query_ball_point(ours.xy_px, r=1.0)
    q = query.descriptors.astype(np.float32)

    def nearest(desc: NDArray[np.uint8]) -> F64:
        d = desc.astype(np.float32)
        return np.array([np.linalg.norm(q[g] - d[i], axis=1).min()
                         for i, g in enumerate(groups) if g])

    after, before = nearest(ours.descriptors), nearest(stored)
    print(f"\n{int(close.sum())} OpenMVG keypoints within 1 px of pycolmap's, median offset after "
          f"+0.5 {offset.round(3)} px; nearest descriptor distance at the same keypoint: as "
          f"stored mean {before.mean():.1f} (median {np.median(before):.1f}), reordered mean "
          f"{after.mean():.1f} (median {np.median(after):.1f})")
    assert before.mean() > 250 and after.mean() < 40 and np.median(after) < 20


def test_held_out_view_registers_with_fresh_sift(
        model: SparseModel, regions: dict[str, ImageFeatures], query: ImageFeatures) -> None:
    truth = model.image_by_name(HELD_OUT)
    assert truth is not None
    held_out = model_without_images(model, [HELD_OUT])
    index = build_descriptor_index(held_out, regions, RegistrationOptions())
    camera = model.cameras[truth.camera_id]
    res = register_image(query, camera, index, RegistrationOptions())
    assert res.success, res.reason
    assert res.cam_from_world is not None
    rot = rotation_angle_deg(res.cam_from_world.R, truth.cam_from_world.R)
    rel = np.linalg.norm(res.cam_from_world.center - truth.cam_from_world.center) / model.extent
    # Fresh COLMAP-convention keypoints of the inliers against the OpenMVG pose: centred
    # with the +0.5 conversion, half a pixel off without it.
    proj = camera.project(truth.cam_from_world.transform(res.inlier_xyz))
    proj_raw = _shift_pp(camera, -0.5).project(truth.cam_from_world.transform(res.inlier_xyz))
    off = np.median(res.inlier_xy_px - proj, axis=0)
    off_raw = np.median(res.inlier_xy_px - proj_raw, axis=0)
    print(f"\n{HELD_OUT}: index {index.num_descriptors} descriptors / {index.num_points} points; "
          f"{res.num_features} query features, {res.num_matches} matches, {res.num_inliers} "
          f"inliers, RMS {res.reproj_error_px:.3f} px; rotation error {rot:.4f}°, centre error "
          f"{100 * rel:.4f} % of extent {model.extent:.3f}; inlier keypoints − OpenMVG projection:"
          f" median {off.round(3)} px (without +0.5: {off_raw.round(3)} px)")
    assert rot < 0.5 and rel < 0.01
    assert res.num_inliers >= 200 and res.reproj_error_px < 2.0
    assert np.all(np.abs(off) < 0.2) and np.all(off_raw > 0.4)
    # The descriptors as stored (VLFeat bin order) do not match pycolmap SIFT.
    raw = {k: ImageFeatures(f.xy_px, f.descriptors[:, np.argsort(VLFEAT_TO_COLMAP)])
           for k, f in regions.items()}
    bad = register_image(query, camera, build_descriptor_index(held_out, raw,
                                                               RegistrationOptions()),
                         RegistrationOptions())
    print(f"stored bin order: {bad.num_matches} matches, {bad.num_inliers} inliers ({bad.reason})")
    assert not bad.success and bad.num_inliers < 30


def test_rescaled_sfm_data(tmp_path: Path, model: SparseModel) -> None:
    before = _sha(SFM)
    s = 2.5
    out = write_scaled_openmvg_sfm_data(SFM, tmp_path / "scaled" / "sfm_data.json", s)
    assert out == tmp_path / "scaled" / "sfm_data.json" and _sha(SFM) == before
    scaled = read_openmvg_sfm_data(out, OMVG / "matches")
    assert scaled.cameras.keys() == model.cameras.keys()
    for cid, cam in model.cameras.items():
        np.testing.assert_array_equal(scaled.cameras[cid].params, cam.params)
    for iid, im in model.images.items():
        sim = scaled.images[iid]
        assert sim.name == im.name and sim.camera_id == im.camera_id
        np.testing.assert_array_equal(sim.cam_from_world.R, im.cam_from_world.R)
        np.testing.assert_allclose(sim.cam_from_world.center, s * im.cam_from_world.center,
                                   rtol=1e-15, atol=0)
        np.testing.assert_array_equal(sim.xy_px, im.xy_px)
        np.testing.assert_array_equal(sim.point3D_ids, im.point3D_ids)
    np.testing.assert_array_equal(scaled.point3D_ids, model.point3D_ids)
    np.testing.assert_allclose(scaled.points_xyz, s * model.points_xyz, rtol=1e-15, atol=0)
    # Byte level: only the 3 × (poses + landmarks) numbers differ; the rest is identical.
    a, b = SFM.read_text(), out.read_text()
    assert NUMBER.sub("#", a) == NUMBER.sub("#", b)
    changed = sum(x != y for x, y in zip(NUMBER.findall(a), NUMBER.findall(b), strict=True))
    assert changed == 3 * (4 + 365)
    # Parsed: everything but the scaled fields equal, key order included.
    da, db = json.loads(a), json.loads(b)
    for doc in (da, db):
        for e in doc["extrinsics"]:
            e["value"]["center"] = None
        for e in doc["structure"]:
            e["value"]["X"] = None
    assert json.dumps(da) == json.dumps(db)
    # The exact (entry by entry) walk that backs up the regex gives the same bytes.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(openmvg, "_fast_spans", lambda *args: None)
        slow = write_scaled_openmvg_sfm_data(SFM, tmp_path / "slow" / "sfm_data.json", s)
    assert slow.read_bytes() == out.read_bytes()
    # Scale 1: a byte-identical copy.
    same = write_scaled_openmvg_sfm_data(SFM, tmp_path / "one" / "sfm_data.json", 1.0)
    assert _sha(same) == before
    copied = shutil.copy(SFM, tmp_path / "sfm_data.json")
    with pytest.raises(InputError, match="overwrite"):
        write_scaled_openmvg_sfm_data(copied, copied, 2.0)
    with pytest.raises(InputError, match="positive"):
        write_scaled_openmvg_sfm_data(SFM, tmp_path / "x.json", 0.0)
    broken = tmp_path / "broken.json"
    broken.write_text(SFM.read_text()[:-200])
    with pytest.raises(InputError, match="corrupt JSON") as e:
        write_scaled_openmvg_sfm_data(broken, tmp_path / "y.json", 2.0)
    assert e.value.path == str(broken)
    with pytest.raises(InputError, match="not found"):
        write_scaled_openmvg_sfm_data(tmp_path / "none.json", tmp_path / "z.json", 2.0)


# --------------------------------------------------------------------------- camera models


def _openmvg_project(name: str, d: dict[str, Any], xyz: F64) -> F64:
    """OpenMVG's projection (its camera code, re-derived), in COLMAP pixels (+0.5)."""
    p = xyz[:, :2] / xyz[:, 2:]
    x, y = p[:, 0], p[:, 1]
    r2 = x * x + y * y
    if name in ("pinhole", "pinhole_2"):
        q = p
    elif name == "pinhole_radial_k1":
        q = p * (1 + d["disto_k1"][0] * r2)[:, None]
    elif name == "pinhole_radial_k3":
        k1, k2, k3 = d["disto_k3"]
        q = p * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3)[:, None]
    elif name in ("pinhole_brown_t2", "pinhole_brown_t2_2"):
        k1, k2, k3, t1, t2 = d["disto_t2" if name == "pinhole_brown_t2" else "disto_t2_2"]
        radial = k1 * r2 + k2 * r2**2 + k3 * r2**3
        q = np.column_stack([x + x * radial + t2 * (r2 + 2 * x * x) + 2 * t1 * x * y,
                             y + y * radial + t1 * (r2 + 2 * y * y) + 2 * t2 * x * y])
    elif name == "fisheye":
        k1, k2, k3, k4 = d["fisheye"]
        r = np.sqrt(r2)
        th = np.arctan(r)
        th_d = th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
        q = p * (th_d / r)[:, None]
    elif name == "fisheye1":
        (w,) = d["fisheye1"]
        r = np.sqrt(r2)
        q = p * (np.arctan(2 * r * np.tan(w / 2)) / w / r)[:, None]
    else:
        raise AssertionError(name)
    fl = d["focal_length"]
    fx, fy = (float(fl), float(fl)) if isinstance(fl, float) else (float(fl[0]), float(fl[1]))
    return np.column_stack([fx * q[:, 0], fy * q[:, 1]]) + np.asarray(d["principal_point"]) + 0.5


INTRINSICS: dict[str, dict[str, Any]] = {
    "pinhole": {},
    "pinhole_radial_k1": {"disto_k1": [-0.12]},
    "pinhole_radial_k3": {"disto_k3": [-0.15, 0.19, 0.012]},
    "pinhole_brown_t2": {"disto_t2": [-0.11, 0.07, -0.01, 0.004, -0.0025]},
    "fisheye": {"fisheye": [0.05, -0.01, 0.003, -0.0005]},
    "fisheye1": {"fisheye1": [0.9]},
    "pinhole_2": {},
    "pinhole_brown_t2_2": {"disto_t2_2": [-0.11, 0.07, -0.01, -0.003, 0.0045]},
}


def _intrinsic_data(name: str, extra: dict[str, Any]) -> dict[str, Any]:
    two = name.endswith("_2")
    base = {"width": 1600, "height": 1200,
            "focal_length": [1510.0, 1490.0] if two else 1500.0,
            "principal_point": [810.25, 590.75]}
    if name == "pinhole_brown_t2":  # newer cereal nests the base class under value0
        return {"value0": base, **extra}
    return {**base, **extra}


def _ptr(type_id: int | None, name: str | None, obj_id: int, data: dict[str, Any] | None
         ) -> dict[str, Any]:
    value: dict[str, Any] = {"polymorphic_id": 0x40000000 if type_id is None else type_id}
    if name is not None:
        value["polymorphic_name"] = name
    value["ptr_wrapper"] = {"id": obj_id} if data is None else {"id": obj_id, "data": data}
    return value


def _view(vid: int, intrinsic: int, pose: int, **extra: Any) -> dict[str, Any]:
    return {"local_path": "", "filename": f"img_{vid:02d}.jpg", "width": 1600, "height": 1200,
            "id_view": vid, "id_intrinsic": intrinsic, "id_pose": pose, **extra}


def _rotation(seed: int) -> list[list[float]]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.random.default_rng(seed).normal(0, 0.2, 3)).as_matrix().tolist()


def _synthetic_doc() -> dict[str, Any]:
    """An sfm_data with every supported intrinsic, shared intrinsics and poses, a view
    without pose, a view with a pose-centre prior, structure and a control point."""
    intrinsics, views, obj = [], [], 0x80000001
    for k, (name, extra) in enumerate(INTRINSICS.items()):
        intrinsics.append({"key": k, "value": _ptr(0x80000001 + k, name,
                                                   obj, _intrinsic_data(name, extra))})
        obj += 1
    # A second pinhole_radial_k3: its type is named only by id (no polymorphic_name).
    intrinsics.append({"key": 8, "value": _ptr(3, None, obj, _intrinsic_data(
        "pinhole_radial_k3", {"disto_k3": [0.01, 0.0, 0.0]}))})
    obj += 1
    for k in range(9):
        views.append({"key": k, "value": _ptr(None, None, obj, _view(k, k, k))})
        obj += 1
    views.append({"key": 9, "value": _ptr(None, None, obj, _view(9, 0, 0))})  # shares pose 0
    views.append({"key": 10, "value": _ptr(None, None, obj + 1, _view(10, 0, 4294967295))})
    prior = _view(11, 2, 5, use_pose_center_prior=True, center_weight=[1.0, 1.0, 1.0],
                  center=[100.0, 200.0, 300.0])
    views.append({"key": 11, "value": _ptr(0x80000000 + 20, "view_priors", obj + 2, prior)})
    extrinsics = [{"key": k, "value": {"rotation": _rotation(k), "center": [0.1 * k, -0.2, 1.5]}}
                  for k in range(9)]
    structure = [{"key": 7, "value": {"X": [0.5, -0.25, 4.0], "observations": [
        {"key": 9, "value": {"id_feat": 12, "x": [100.0, 200.0]}},
        {"key": 0, "value": {"id_feat": 3, "x": [110.0, 210.0]}},
        {"key": 10, "value": {"id_feat": 5, "x": [1.0, 2.0]}}]}},  # view 10: no pose
        {"key": 3, "value": {"X": [1.0, 2.0, 6.0], "observations": [
            {"key": 9, "value": {"id_feat": 4, "x": [300.0, 400.0]}},
            {"key": 1, "value": {"id_feat": 0, "x": [310.0, 410.0]}}]}}]
    control = [{"key": 0, "value": {"X": [10.0, 20.0, 30.0], "observations": [
        {"key": 0, "value": {"id_feat": 0, "x": [5.0, 6.0]}}]}}]
    return {"sfm_data_version": "0.3", "root_path": "/data/images", "views": views,
            "intrinsics": intrinsics, "extrinsics": extrinsics, "structure": structure,
            "control_points": control}


def _write(doc: dict[str, Any], path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=4) + "\n")
    return path


def test_every_supported_camera_model_projects_like_openmvg(tmp_path: Path) -> None:
    scene = parse_openmvg_sfm_data(_write(_synthetic_doc(), tmp_path / "sfm_data.json"))
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(-0.5, 0.5, (200, 2)), np.ones(200)]) * rng.uniform(
        2, 6, (200, 1))
    expected_models = ["PINHOLE", "SIMPLE_RADIAL", "FULL_OPENCV", "FULL_OPENCV",
                       "OPENCV_FISHEYE", "FOV", "PINHOLE", "FULL_OPENCV"]
    worst = 0.0
    for k, (name, extra) in enumerate(INTRINSICS.items()):
        cam = scene.cameras[k]
        assert cam.model == expected_models[k], name
        want = _openmvg_project(name, {**_intrinsic_data(name, extra).get("value0", {}),
                                       **_intrinsic_data(name, extra)}, xyz)
        err = np.abs(cam.project(xyz) - want).max()
        worst = max(worst, float(err))
        assert err < 1e-6, f"{name}: {err} px"
    print(f"\nworst difference to OpenMVG's projection over 8 camera models: {worst:.2e} px")
    assert scene.cameras[8].model == "FULL_OPENCV" and scene.cameras[8].params[4] == 0.01


def test_synthetic_views_poses_structure_and_observation_layout(tmp_path: Path) -> None:
    path = _write(_synthetic_doc(), tmp_path / "sfm_data.json")
    model = read_openmvg_sfm_data(path)  # no regions anywhere: observations only
    assert sorted(model.images) == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 11]  # view 10 has no pose
    assert model.images[9].cam_from_world is model.images[0].cam_from_world
    assert model.images[9].camera_id == 0 and model.images[11].camera_id == 2
    np.testing.assert_allclose(model.images[3].cam_from_world.center, [0.3, -0.2, 1.5])
    im9 = model.images[9]  # observations sorted by feature id (4, then 12), +0.5 px
    np.testing.assert_array_equal(im9.xy_px, [[300.5, 400.5], [100.5, 200.5]])
    np.testing.assert_array_equal(im9.point3D_ids, [3, 7])
    np.testing.assert_array_equal(model.point3D_ids, [7, 3])
    # Rescaling: pose centres, landmark X and control points X; the view prior is untouched.
    out = write_scaled_openmvg_sfm_data(path, tmp_path / "out" / "sfm_data.json", 3.0)
    doc, new = _synthetic_doc(), json.loads(out.read_text())
    assert new["views"][11]["value"]["ptr_wrapper"]["data"]["center"] == [100.0, 200.0, 300.0]
    assert new["control_points"][0]["value"]["X"] == [30.0, 60.0, 90.0]
    assert new["structure"][1]["value"]["X"] == [3.0, 6.0, 18.0]
    assert new["extrinsics"][2]["value"]["center"] == pytest.approx([0.6, -0.6, 4.5])
    ref = copy.deepcopy(doc)
    for d in (ref, new):
        for sec, key in (("extrinsics", "center"), ("structure", "X"), ("control_points", "X")):
            for e in d[sec]:
                e["value"][key] = None
    assert new == ref


def test_descriptor_conversion_between_rootsift_and_l2() -> None:
    # The permutation reverses the 8 orientation bins of each spatial cell, keeping bin 0.
    d = np.arange(128, dtype=np.uint8)[None]
    np.testing.assert_array_equal(d[0, VLFEAT_TO_COLMAP][8:16], [8, 15, 14, 13, 12, 11, 10, 9])
    np.testing.assert_array_equal(d[0, VLFEAT_TO_COLMAP][VLFEAT_TO_COLMAP], d[0])  # involution
    # Synthetic SIFT histograms (COLMAP order), L2-normalised and clipped at 0.2 like VLFeat.
    rng = np.random.default_rng(5)
    h = rng.gamma(0.6, 1.0, (500, 128))
    for _ in range(2):
        h = np.minimum(h / np.linalg.norm(h, axis=1, keepdims=True), 0.2)
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    root = np.sqrt(h / h.sum(axis=1, keepdims=True))
    colmap = {"L2": np.round(512 * h), "L1_ROOT": np.round(512 * root)}  # COLMAP's storage
    vl = np.argsort(VLFEAT_TO_COLMAP)  # COLMAP order -> VLFeat order
    openmvg = {True: np.floor(512 * root)[:, vl].astype(np.uint8),  # OpenMVG truncates
               False: np.floor(512 * h)[:, vl].astype(np.uint8)}
    for root_sift, stored in openmvg.items():
        for norm, want in colmap.items():
            got = openmvg_sift_to_colmap(stored, root_sift, norm).astype(np.float64)
            dist = np.linalg.norm(got - want, axis=1)
            scramble = np.linalg.norm(stored.astype(np.float64) - want, axis=1)
            print(f"\nroot_sift={root_sift} -> {norm}: mean distance {dist.mean():.2f} "
                  f"(unconverted {scramble.mean():.1f})")
            assert dist.mean() < 15 and scramble.mean() > 20 * dist.mean()
    with pytest.raises(InputError):
        openmvg_sift_to_colmap(openmvg[True], True, "L3")


# --------------------------------------------------------------------------- errors


def _copy_fixture(tmp_path: Path) -> Path:
    dst = tmp_path / "omvg"
    shutil.copytree(OMVG / "matches", dst / "matches")
    shutil.copy(SFM, dst / "sfm_data.json")
    for p in dst.rglob("*"):
        p.chmod(0o644)
    return dst / "sfm_data.json"


def test_bad_inputs_are_input_errors_naming_the_file(tmp_path: Path) -> None:
    doc = _synthetic_doc()
    doc["intrinsics"][0]["value"]["polymorphic_name"] = "spherical"
    bad = _write(doc, tmp_path / "a" / "sfm_data.json")
    with pytest.raises(InputError, match="'spherical' is not supported") as e:
        read_openmvg_sfm_data(bad)
    assert e.value.path == str(bad)
    with pytest.raises(InputError, match="not found"):
        read_openmvg_sfm_data(tmp_path / "missing" / "sfm_data.json")
    sfm = _copy_fixture(tmp_path)
    text = sfm.read_text()
    sfm.write_text(text[: len(text) // 2])
    with pytest.raises(InputError, match="corrupt JSON") as e:
        read_openmvg_sfm_data(sfm)
    assert e.value.path == str(sfm)
    sfm.write_text(text)
    with pytest.raises(InputError, match="ConvertSfM_DataFormat"):
        parse_openmvg_sfm_data(tmp_path / "sfm_data.bin")
    nopose = copy.deepcopy(doc)
    nopose["extrinsics"] = []
    with pytest.raises(InputError, match="no view has a pose"):
        read_openmvg_sfm_data(_write(nopose, tmp_path / "b" / "sfm_data.json"))
    with pytest.raises(InputError, match="not an OpenMVG sfm_data"):
        read_openmvg_sfm_data(_write({"a": 1}, tmp_path / "c" / "sfm_data.json"))


def test_missing_or_corrupt_regions(tmp_path: Path) -> None:
    sfm = _copy_fixture(tmp_path)
    matches = sfm.parent / "matches"
    with pytest.raises(InputError, match="regions file not found") as e:
        read_openmvg_sfm_data(sfm, tmp_path / "empty")
    assert e.value.path is not None and e.value.path.endswith("MaupertuisTest_01.feat")
    model = read_openmvg_sfm_data(sfm)
    (matches / "MaupertuisTest_02.desc").unlink()
    with pytest.raises(InputError, match="not found") as e:
        openmvg_model_features(model, sfm, matches)
    assert e.value.path == str(matches / "MaupertuisTest_02.desc")
    raw = (OMVG / "matches" / "MaupertuisTest_02.desc").read_bytes()
    (matches / "MaupertuisTest_02.desc").write_bytes(raw[:-100])
    with pytest.raises(InputError, match="corrupt .desc") as e:
        openmvg_model_features(model, sfm, matches)
    assert e.value.path == str(matches / "MaupertuisTest_02.desc")
    (matches / "MaupertuisTest_02.desc").write_bytes(raw)
    # .feat of another image: observations do not sit on its keypoints -> error when given,
    # observation-only model (and a warning) when the regions were only found beside it.
    shutil.copy(OMVG / "matches" / "MaupertuisTest_04.feat", matches / "MaupertuisTest_01.feat")
    with pytest.raises(InputError, match="another run") as e:
        read_openmvg_sfm_data(sfm, matches)
    assert e.value.path == str(matches / "MaupertuisTest_01.feat")
    loose = read_openmvg_sfm_data(sfm)
    assert len(loose.images[0].xy_px) == 239
    shutil.copy(OMVG / "matches" / "MaupertuisTest_01.feat", matches / "MaupertuisTest_01.feat")
    describer = json.loads((matches / "image_describer.json").read_text())
    describer["image_describer"]["polymorphic_name"] = "AKAZE_Image_describer_MLDB"
    (matches / "image_describer.json").write_text(json.dumps(describer))
    with pytest.raises(InputError, match="AKAZE") as e:
        read_openmvg_regions(matches, ["MaupertuisTest_01"])
    assert e.value.path == str(matches / "image_describer.json")


# --------------------------------------------------------------------------- dispatcher


def test_dispatcher_loads_openmvg_models_and_their_regions(tmp_path: Path) -> None:
    model = load_model(SFM)
    assert model.source_format == "openmvg" and len(model.images) == 4
    assert find_openmvg_regions_dir(SFM) == OMVG / "matches"
    feats = load_model_features(model, SFM, None, None, None, TieOptions())
    assert set(feats) == {im.name for im in model.images.values()}
    assert all(isinstance(f, ImageFeatures) for f in feats.values())
    full = build_descriptor_index(model, feats, RegistrationOptions())
    # sfm_data alone (OpenMVG's own layout has matches/ elsewhere): observation layout,
    # regions through --features.
    alone = Path(shutil.copy(SFM, tmp_path / "sfm_data.json"))
    obs_model = load_model(alone)
    assert len(obs_model.images[3].xy_px) == 269
    tied = load_model_features(obs_model, alone, None, None, OMVG / "matches", TieOptions())
    assert all(isinstance(f, ObservationFeatures) for f in tied.values())
    index = build_descriptor_index(obs_model, tied, RegistrationOptions())
    assert index.num_descriptors == full.num_descriptors and index.num_points == 365
    np.testing.assert_array_equal(np.sort(index.descriptors, axis=0),
                                  np.sort(full.descriptors, axis=0))
    with pytest.raises(InputError, match="--features DIR or --images"):
        load_model_features(obs_model, alone, None, None, None, TieOptions())
    with pytest.raises(InputError, match="COLMAP database"):
        load_model_features(model, SFM, tmp_path / "x.db", None, None, TieOptions())


def test_scale_outputs_write_the_rescaled_sfm_data(tmp_path: Path) -> None:
    """report.writer dispatches the rescaled model by the loaded model's format."""
    from types import SimpleNamespace

    from sfm_laserscale.report.writer import _write_scaled

    mesh = tmp_path / "mesh.ply"
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                    "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    inputs = SimpleNamespace(model=SFM, mesh=mesh)
    loaded = SimpleNamespace(model=SimpleNamespace(source_format="openmvg"))
    out = tmp_path / "out"
    out.mkdir()
    _write_scaled(out, inputs, loaded, 0.5, False)  # type: ignore[arg-type]
    scaled = read_openmvg_sfm_data(out / "scaled" / "model" / "sfm_data.json", OMVG / "matches")
    original = read_openmvg_sfm_data(SFM)
    np.testing.assert_allclose(scaled.points_xyz, 0.5 * original.points_xyz, rtol=1e-15)
    assert (out / "scaled" / "mesh.ply").is_file()
