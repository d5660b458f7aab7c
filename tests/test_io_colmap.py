"""COLMAP sparse model I/O: real fixture, pycolmap 4.2-written models, lossless rescale, errors."""

from __future__ import annotations

import re
import shutil
import struct
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sfm_laserscale.errors import InputError
from sfm_laserscale.geometry import rotmat_from_qvec
from sfm_laserscale.io.colmap import detect_colmap_format, model_without_images, read_colmap_model
from sfm_laserscale.io.colmap_write import (
    write_colmap_model_binary,
    write_colmap_model_text,
    write_scaled_colmap_model,
)
from sfm_laserscale.model import INVALID_POINT3D_ID, Camera, Image, Pose, SparseModel

FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures"
RECON = FIXTURES / "maupertuis_colmap" / "reconstruction"
SCALE = 0.0372519  # an arbitrary metres-per-unit


# ----------------------------------------------------------------------------- helpers


@pytest.fixture(scope="module")
def fixture_model() -> SparseModel:
    return read_colmap_model(RECON)


@pytest.fixture
def text_copy(tmp_path: Path) -> Path:
    dst = tmp_path / "text_model"
    shutil.copytree(RECON, dst)
    for f in dst.iterdir():
        f.chmod(0o644)
    dst.chmod(0o755)
    return dst


@pytest.fixture
def binary_copy(tmp_path: Path, fixture_model: SparseModel) -> Path:
    dst = tmp_path / "binary_model"
    write_colmap_model_binary(fixture_model, dst)
    return dst


def _pycolmap_folder(tmp_path: Path, binary: bool, rec: pycolmap.Reconstruction) -> Path:
    dst = tmp_path / ("pyc_bin" if binary else "pyc_txt")
    dst.mkdir()
    if binary:
        rec.write(str(dst))
    else:
        rec.write_text(str(dst))
    return dst


def _rig_reconstruction() -> pycolmap.Reconstruction:
    """A COLMAP 4 reconstruction with 2-camera rigs (non-identity sensor_from_rig)."""
    opt = pycolmap.SyntheticDatasetOptions(num_rigs=2, num_cameras_per_rig=2,
                                           num_frames_per_rig=3, num_points3D=60)
    return pycolmap.synthesize_dataset(opt)


def _assert_same_model(a: SparseModel, b: SparseModel, exact_rotation: bool = False) -> None:
    """Equal cameras, images (poses, observations) and points, whatever the file order."""
    assert a.cameras.keys() == b.cameras.keys()
    for cid, ca in a.cameras.items():
        cb = b.cameras[cid]
        assert (ca.model, ca.width, ca.height) == (cb.model, cb.width, cb.height)
        np.testing.assert_array_equal(ca.params, cb.params)
    assert a.images.keys() == b.images.keys()
    for iid, ia in a.images.items():
        ib = b.images[iid]
        assert (ia.name, ia.camera_id) == (ib.name, ib.camera_id)
        np.testing.assert_array_equal(ia.cam_from_world.t, ib.cam_from_world.t)
        if exact_rotation:
            np.testing.assert_array_equal(ia.cam_from_world.R, ib.cam_from_world.R)
        else:
            np.testing.assert_allclose(ia.cam_from_world.R, ib.cam_from_world.R, atol=1e-14)
        np.testing.assert_array_equal(ia.xy_px, ib.xy_px)
        assert ia.point3D_ids.dtype == np.uint64
        np.testing.assert_array_equal(ia.point3D_ids, ib.point3D_ids)
    oa, ob = np.argsort(a.point3D_ids), np.argsort(b.point3D_ids)
    np.testing.assert_array_equal(a.point3D_ids[oa], b.point3D_ids[ob])
    np.testing.assert_array_equal(a.points_xyz[oa], b.points_xyz[ob])


def _reprojection_errors(model: SparseModel) -> np.ndarray:
    errs = []
    for im in model.images.values():
        has = im.point3D_ids != INVALID_POINT3D_ID
        rows = [model.point_index[int(p)] for p in im.point3D_ids[has]]
        xyz_cam = im.cam_from_world.transform(model.points_xyz[rows])
        uv = model.cameras[im.camera_id].project(xyz_cam)
        errs.append(np.linalg.norm(uv - im.xy_px[has], axis=1))
    return np.concatenate(errs)


def _assert_model_from_pycolmap(model: SparseModel, rec: pycolmap.Reconstruction) -> None:
    """Our reading equals pycolmap's own object (poses composed from rigs and frames)."""
    assert set(model.images) == set(rec.images)
    for iid, im in model.images.items():
        ref = rec.images[iid]
        assert (im.name, im.camera_id) == (ref.name, ref.camera_id)
        pose = ref.cam_from_world()
        # pycolmap keeps the file's quaternion unnormalised (|q| - 1 ~ 4e-7 on the fixture's
        # 6-digit text), so its matrix is not quite a rotation: compare with the unit q.
        x, y, z, w = pose.rotation.quat
        np.testing.assert_allclose(im.cam_from_world.R, rotmat_from_qvec(np.array([w, x, y, z])),
                                   atol=1e-12)
        np.testing.assert_allclose(im.cam_from_world.t, pose.translation, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(im.xy_px, np.array([p.xy for p in ref.points2D]))
    for pid, p in rec.points3D.items():
        np.testing.assert_array_equal(model.points_xyz[model.point_index[pid]], p.xyz)


# ----------------------------------------------------------------------------- reading


def test_fixture_counts_and_reprojection(fixture_model: SparseModel) -> None:
    m = fixture_model
    assert m.source_format == "colmap-text"
    assert (len(m.cameras), len(m.images), len(m.points_xyz)) == (1, 4, 1039)
    assert sorted(im.name for im in m.images.values()) == ["00.jpg", "01.jpg", "02.jpg", "03.jpg"]
    assert m.point3D_ids.dtype == np.uint64 and m.points_xyz.shape == (1039, 3)
    n_obs = sum(int(np.sum(im.point3D_ids != INVALID_POINT3D_ID)) for im in m.images.values())
    assert n_obs == 3355  # COLMAP's own summary of this model
    err = _reprojection_errors(m)
    # COLMAP reports 0.3426 px mean; the text file's 6 significant digits add a little.
    assert err.mean() < 0.5 and np.median(err) < 0.5
    # the same check with the inverse pose (a convention mix-up) fails badly
    im = m.images[1]
    has = im.point3D_ids != INVALID_POINT3D_ID
    xyz = im.cam_from_world.inverse().transform(
        m.points_xyz[[m.point_index[int(p)] for p in im.point3D_ids[has]]])
    front = xyz[:, 2] > 0
    if front.any():
        wrong = m.cameras[1].project(xyz[front]) - im.xy_px[has][front]
        assert np.linalg.norm(wrong, axis=1).mean() > 10


def test_fixture_matches_pycolmap(fixture_model: SparseModel) -> None:
    _assert_model_from_pycolmap(fixture_model, pycolmap.Reconstruction(str(RECON)))


@pytest.mark.parametrize("binary", [True, False])
def test_reads_pycolmap_4_2_fixture_model(tmp_path: Path, fixture_model: SparseModel,
                                          binary: bool) -> None:
    folder = _pycolmap_folder(tmp_path, binary, pycolmap.Reconstruction(str(RECON)))
    assert (folder / ("rigs.bin" if binary else "rigs.txt")).is_file()  # a COLMAP 4 folder
    m = read_colmap_model(folder)
    assert m.source_format == ("colmap-binary" if binary else "colmap-text")
    if binary:  # doubles written by pycolmap are the fixture's, bit for bit
        _assert_same_model(m, fixture_model)
    _assert_model_from_pycolmap(m, pycolmap.Reconstruction(str(RECON)))


@pytest.mark.parametrize("binary", [True, False])
def test_reads_pycolmap_4_2_rig_model(tmp_path: Path, binary: bool) -> None:
    rec = _rig_reconstruction()
    m = read_colmap_model(_pycolmap_folder(tmp_path, binary, rec))
    assert len(m.images) == 12 and len(m.cameras) == 4
    _assert_model_from_pycolmap(m, rec)
    assert _reprojection_errors(m).max() < 1e-6  # synthetic: exact observations


def test_binary_preferred_when_both_formats(tmp_path: Path, fixture_model: SparseModel) -> None:
    write_colmap_model_text(fixture_model, tmp_path)
    assert detect_colmap_format(tmp_path) == "colmap-text"
    write_colmap_model_binary(fixture_model, tmp_path)
    assert read_colmap_model(tmp_path).source_format == "colmap-binary"


# ----------------------------------------------------------------------------- writers


def test_round_trip_text_binary_text(tmp_path: Path, fixture_model: SparseModel) -> None:
    write_colmap_model_binary(fixture_model, tmp_path / "bin")
    from_bin = read_colmap_model(tmp_path / "bin")
    assert from_bin.source_format == "colmap-binary"
    _assert_same_model(fixture_model, from_bin)
    write_colmap_model_text(from_bin, tmp_path / "txt")
    from_txt = read_colmap_model(tmp_path / "txt")
    _assert_same_model(fixture_model, from_txt)
    _assert_same_model(from_bin, from_txt)


@pytest.mark.parametrize("binary", [True, False])
def test_written_tracks_match_colmap(tmp_path: Path, fixture_model: SparseModel,
                                     binary: bool) -> None:
    """pycolmap reads our files with the same tracks as the original COLMAP model."""
    write = write_colmap_model_binary if binary else write_colmap_model_text
    write(fixture_model, tmp_path)
    ours, ref = pycolmap.Reconstruction(str(tmp_path)), pycolmap.Reconstruction(str(RECON))
    assert ours.num_points3D() == ref.num_points3D() == 1039
    for pid, p in ref.points3D.items():
        q = ours.points3D[pid]
        assert sorted((e.image_id, e.point2D_idx) for e in p.track.elements) == sorted(
            (e.image_id, e.point2D_idx) for e in q.track.elements)
        np.testing.assert_array_equal(p.xyz, q.xyz)
        assert tuple(q.color) == (128, 128, 128) and q.error == 0
    for iid, im in ref.images.items():  # same poses (the fixture's q is unit to ~4e-7)
        np.testing.assert_allclose(ours.images[iid].cam_from_world().matrix(),
                                   im.cam_from_world().matrix(), atol=2e-6)


def test_writer_keeps_newer_camera_models_and_empty_observations(tmp_path: Path) -> None:
    cams = {3: Camera(3, "SIMPLE_FISHEYE", 640, 480, np.array([300.0, 320.0, 240.0])),
            7: Camera(7, "OPENCV", 640, 480, np.arange(8, dtype=float) + 0.5)}
    images = {5: Image(5, "a b.jpg", 3, Pose(np.eye(3), np.array([1.0, -2.0, 3e-9]))),
              9: Image(9, "c.jpg", 7, Pose(np.eye(3), np.zeros(3)), np.array([[1.5, 2.5]]),
                       np.array([INVALID_POINT3D_ID], dtype=np.uint64))}
    model = SparseModel(cams, images, np.zeros(0, np.uint64), np.zeros((0, 3)))
    for write in (write_colmap_model_binary, write_colmap_model_text):
        write(model, tmp_path / write.__name__)
        _assert_same_model(model, read_colmap_model(tmp_path / write.__name__), True)


# ----------------------------------------------------------------------------- hold-out


def test_model_without_images(fixture_model: SparseModel) -> None:
    held = model_without_images(fixture_model, ["03.jpg"])
    assert sorted(im.name for im in held.images.values()) == ["00.jpg", "01.jpg", "02.jpg"]
    ref = pycolmap.Reconstruction(str(RECON))
    held_id = next(i for i, im in ref.images.items() if im.name == "03.jpg")
    expected = {pid for pid, p in ref.points3D.items()
                if sum(e.image_id != held_id for e in p.track.elements) >= 2}
    assert set(held.point3D_ids.tolist()) == expected and 0 < len(expected) < 1039
    counts: dict[int, int] = {}
    for im in held.images.values():
        orig = fixture_model.images[im.image_id]
        np.testing.assert_array_equal(im.xy_px, orig.xy_px)
        for new, old in zip(im.point3D_ids.tolist(), orig.point3D_ids.tolist(), strict=True):
            assert new in (old, INVALID_POINT3D_ID)
            if new != INVALID_POINT3D_ID:
                counts[new] = counts.get(new, 0) + 1
            elif old != INVALID_POINT3D_ID:
                assert old not in expected
    assert set(counts) == expected and min(counts.values()) >= 2
    np.testing.assert_array_equal(
        held.points_xyz, fixture_model.points_xyz[np.isin(fixture_model.point3D_ids,
                                                          held.point3D_ids)])
    with pytest.raises(InputError, match="nope.jpg"):
        model_without_images(fixture_model, ["nope.jpg"])


def test_model_without_observations(fixture_model: SparseModel) -> None:
    """Cameras, poses, points and the extent stay; only the 2D observations go."""
    light = fixture_model.without_observations()
    assert light.cameras == fixture_model.cameras
    assert light.source_format == fixture_model.source_format
    assert light.extent == fixture_model.extent
    np.testing.assert_array_equal(light.points_xyz, fixture_model.points_xyz)
    np.testing.assert_array_equal(light.point3D_ids, fixture_model.point3D_ids)
    assert light.images.keys() == fixture_model.images.keys()
    for k, im in light.images.items():
        orig = fixture_model.images[k]
        assert (im.name, im.camera_id, im.image_id) == (orig.name, orig.camera_id, orig.image_id)
        np.testing.assert_array_equal(im.cam_from_world.R, orig.cam_from_world.R)
        np.testing.assert_array_equal(im.cam_from_world.t, orig.cam_from_world.t)
        assert im.xy_px.shape == (0, 2) and im.point3D_ids.shape == (0,)
        assert len(orig.xy_px) > 0  # the source model keeps its observations


# ----------------------------------------------------------------------------- rescale


def _split_lines(path: Path) -> list[bytes]:
    return path.read_bytes().splitlines(keepends=True)


def test_scaled_text_is_lossless(text_copy: Path, tmp_path: Path,
                                 fixture_model: SparseModel) -> None:
    (text_copy / "project.ini").write_bytes(b"[General]\r\nfoo=1\r\n")
    dst = tmp_path / "scaled"
    written = write_scaled_colmap_model(text_copy, dst, SCALE)
    assert sorted(p.name for p in written) == [
        "cameras.txt", "images.txt", "points3D.txt", "project.ini"]
    for name in ("cameras.txt", "project.ini"):
        assert (dst / name).read_bytes() == (text_copy / name).read_bytes()
    scaled = read_colmap_model(dst)
    _check_scaled(fixture_model, scaled, SCALE)
    # byte level: only fields 5-7 of pose lines and 1-3 of point lines differ
    for name, first, is_data in (("images.txt", 5, _pose_line_mask),
                                 ("points3D.txt", 1, _data_line_mask)):
        src, out = _split_lines(text_copy / name), _split_lines(dst / name)
        assert len(src) == len(out)
        mask = is_data(src)
        assert sum(mask) == (4 if name == "images.txt" else 1039)
        for a, b, data in zip(src, out, mask, strict=True):
            if not data:
                assert a == b
                continue
            ta, tb = a.split(b" "), b.split(b" ")
            assert len(ta) == len(tb) and a[-1:] == b[-1:] == b"\n"
            assert ta[:first] + ta[first + 3:] == tb[:first] + tb[first + 3:]
            for x, y in zip(ta[first:first + 3], tb[first:first + 3], strict=True):
                assert float(y) == pytest.approx(SCALE * float(x), rel=1e-12, abs=0)


def test_scaled_text_keeps_crlf_and_odd_whitespace(text_copy: Path, tmp_path: Path,
                                                   fixture_model: SparseModel) -> None:
    for name in ("images.txt", "points3D.txt"):
        data = (text_copy / name).read_bytes().replace(b"\n", b"\r\n")
        lines = data.splitlines(keepends=True)
        k = next(i for i, li in enumerate(lines) if not li.startswith(b"#"))  # first data line
        lines[k] = b"  " + lines[k].replace(b" ", b"\t ", 3)
        (text_copy / name).write_bytes(b"".join(lines))
    src_model = read_colmap_model(text_copy)
    _assert_same_model(fixture_model, src_model, exact_rotation=True)
    dst = tmp_path / "scaled"
    write_scaled_colmap_model(text_copy, dst, SCALE)
    _check_scaled(src_model, read_colmap_model(dst), SCALE)
    for name, first in (("images.txt", 5), ("points3D.txt", 1)):
        a, b = (text_copy / name).read_bytes(), (dst / name).read_bytes()
        seps_a, seps_b = re.split(rb"\S+", a), re.split(rb"\S+", b)
        assert seps_a == seps_b  # every separator and line ending kept
        tok_a, tok_b = re.findall(rb"\S+", a), re.findall(rb"\S+", b)
        assert len(tok_a) == len(tok_b)
        changed = [i for i, (x, y) in enumerate(zip(tok_a, tok_b, strict=True)) if x != y]
        assert changed and tok_a[changed[0] - first] in (b"708", b"4")  # its first data line


def test_scaled_folder_with_both_formats(binary_copy: Path, tmp_path: Path,
                                         fixture_model: SparseModel) -> None:
    write_colmap_model_text(fixture_model, binary_copy)
    dst = tmp_path / "scaled"
    assert len(write_scaled_colmap_model(binary_copy, dst, SCALE)) == 6
    scaled_bin = read_colmap_model(dst)
    for f in ("cameras.bin", "images.bin", "points3D.bin"):
        (dst / f).unlink()
    _assert_same_model(scaled_bin, read_colmap_model(dst))  # the .txt copy is scaled too


def _data_line_mask(lines: list[bytes]) -> list[bool]:
    return [bool(li.strip()) and not li.startswith(b"#") for li in lines]


def _pose_line_mask(lines: list[bytes]) -> list[bool]:
    mask, after_pose = [], False
    for li in lines:
        is_pose = not after_pose and bool(li.strip()) and not li.startswith(b"#")
        mask.append(is_pose)
        after_pose = is_pose
    return mask


def _check_scaled(orig: SparseModel, scaled: SparseModel, s: float) -> None:
    """Translations and points are s x the original (1e-12 relative); all else identical."""
    assert scaled.source_format == orig.source_format
    assert scaled.cameras.keys() == orig.cameras.keys()
    for cid, cam in orig.cameras.items():
        np.testing.assert_array_equal(scaled.cameras[cid].params, cam.params)
    for iid, im in orig.images.items():
        sc = scaled.images[iid]
        np.testing.assert_array_equal(sc.cam_from_world.R, im.cam_from_world.R)
        np.testing.assert_allclose(sc.cam_from_world.t, s * im.cam_from_world.t, rtol=1e-12,
                                   atol=0)
        np.testing.assert_array_equal(sc.xy_px, im.xy_px)
        np.testing.assert_array_equal(sc.point3D_ids, im.point3D_ids)
    np.testing.assert_array_equal(scaled.point3D_ids, orig.point3D_ids)
    np.testing.assert_allclose(scaled.points_xyz, s * orig.points_xyz, rtol=1e-12, atol=0)


def _images_bin_tvec_bytes(data: bytes) -> list[tuple[int, int]]:
    """Independent walk of images.bin: byte ranges of every tvec."""
    (n,), pos, ranges = struct.unpack_from("<Q", data, 0), 8, []
    for _ in range(n):
        ranges.append((pos + 36, pos + 60))
        end = data.index(b"\0", pos + 64)
        (npts,) = struct.unpack_from("<Q", data, end + 1)
        pos = end + 9 + 24 * npts
    assert pos == len(data)
    return ranges


def _points_bin_xyz_bytes(data: bytes) -> list[tuple[int, int]]:
    """Independent walk of points3D.bin: byte ranges of every xyz."""
    (n,), pos, ranges = struct.unpack_from("<Q", data, 0), 8, []
    for _ in range(n):
        ranges.append((pos + 8, pos + 32))
        (track_len,) = struct.unpack_from("<Q", data, pos + 43)
        pos += 51 + 8 * track_len
    assert pos == len(data)
    return ranges


def _assert_only_ranges_differ(a: bytes, b: bytes, ranges: list[tuple[int, int]]) -> None:
    assert len(a) == len(b)
    allowed = np.zeros(len(a), bool)
    for lo, hi in ranges:
        allowed[lo:hi] = True
    diff = np.frombuffer(a, np.uint8) != np.frombuffer(b, np.uint8)
    assert not np.any(diff & ~allowed)
    assert np.any(diff)


def test_scaled_binary_is_lossless(binary_copy: Path, tmp_path: Path,
                                   fixture_model: SparseModel) -> None:
    (binary_copy / "project.ini").write_text("[General]\n")
    dst = tmp_path / "scaled"
    written = write_scaled_colmap_model(binary_copy, dst, SCALE)
    assert sorted(p.name for p in written) == [
        "cameras.bin", "images.bin", "points3D.bin", "project.ini"]
    for name in ("cameras.bin", "project.ini"):
        assert (dst / name).read_bytes() == (binary_copy / name).read_bytes()
    src_img, out_img = (binary_copy / "images.bin").read_bytes(), (dst / "images.bin").read_bytes()
    _assert_only_ranges_differ(src_img, out_img, _images_bin_tvec_bytes(src_img))
    src_pts, out_pts = (binary_copy / "points3D.bin").read_bytes(), (
        dst / "points3D.bin").read_bytes()
    _assert_only_ranges_differ(src_pts, out_pts, _points_bin_xyz_bytes(src_pts))
    orig = read_colmap_model(binary_copy)
    _check_scaled(orig, read_colmap_model(dst), SCALE)
    np.testing.assert_array_equal(  # scale 1 is an exact copy
        (Path(write_scaled_colmap_model(binary_copy, tmp_path / "one", 1.0)[1])).read_bytes(),
        src_img)


@pytest.mark.parametrize("binary", [True, False])
def test_scaled_colmap4_rig_model(tmp_path: Path, binary: bool) -> None:
    """rigs/frames translations are scaled too: pycolmap (which composes image poses from
    rigs and frames) and our reader (images file) both see the model scaled by s."""
    rec = _rig_reconstruction()
    src = _pycolmap_folder(tmp_path, binary, rec)
    dst = tmp_path / "scaled"
    written = write_scaled_colmap_model(src, dst, SCALE)
    suffix = ".bin" if binary else ".txt"
    assert {p.name for p in written} == {f"{s}{suffix}" for s in (
        "cameras", "images", "points3D", "rigs", "frames")}
    expected = pycolmap.Reconstruction(str(src))
    expected.transform(pycolmap.Sim3d(SCALE, pycolmap.Rotation3d(), np.zeros(3)))
    got = pycolmap.Reconstruction(str(dst))
    for iid, im in expected.images.items():
        np.testing.assert_allclose(got.images[iid].cam_from_world().matrix(),
                                   im.cam_from_world().matrix(), rtol=1e-12, atol=1e-14)
    for rid, rig in expected.rigs.items():
        for sensor, pose in rig.non_ref_sensors.items():
            got_pose = got.rigs[rid].non_ref_sensors[sensor]
            assert pose is not None and got_pose is not None
            np.testing.assert_allclose(got_pose.translation, pose.translation, rtol=1e-12,
                                       atol=1e-15)
    _assert_model_from_pycolmap(read_colmap_model(dst), expected)


def _take_rows(buf: np.ndarray, starts: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """buf[starts[i] + cols] for every i, in blocks (bounded memory)."""
    return np.concatenate([buf[starts[a:a + 100_000, None] + cols]
                           for a in range(0, len(starts), 100_000)])


def test_rescale_one_million_points_binary(tmp_path: Path) -> None:
    """A 1M-point points3D.bin with variable tracks rescales in a few seconds, exactly."""
    rng = np.random.default_rng(7)
    n = 1_000_000
    track_len = rng.integers(2, 7, n)
    sizes = 51 + 8 * track_len
    starts = 8 + np.cumsum(sizes) - sizes
    buf = np.frombuffer(rng.bytes(8 + int(sizes.sum())), np.uint8).copy()  # random tracks
    buf[:8] = np.frombuffer(struct.pack("<Q", n), np.uint8)
    xyz = rng.normal(size=(n, 3))
    for a in range(0, n, 100_000):
        blk = slice(a, a + 100_000)
        buf[starts[blk, None] + np.arange(8, 32)] = xyz[blk].view(np.uint8).reshape(-1, 24)
        buf[starts[blk, None] + np.arange(43, 51)] = (
            track_len[blk].astype("<u8").view(np.uint8).reshape(-1, 8))
    src = tmp_path / "big"
    src.mkdir()
    (src / "points3D.bin").write_bytes(buf.tobytes())
    (src / "cameras.bin").write_bytes(struct.pack("<Q", 0))
    (src / "images.bin").write_bytes(struct.pack("<Q", 0))
    t0, c0 = time.perf_counter(), time.process_time()
    write_scaled_colmap_model(src, tmp_path / "out", SCALE)
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = np.fromfile(tmp_path / "out" / "points3D.bin", np.uint8)
    assert len(out) == len(buf)
    got = _take_rows(out, starts, np.arange(8, 32)).view("<f8")
    np.testing.assert_array_equal(got, xyz * SCALE)
    changed = np.flatnonzero(out != buf)
    offset_in_record = changed - starts[np.searchsorted(starts, changed, side="right") - 1]
    assert np.all((offset_in_record >= 8) & (offset_in_record < 32))
    print(f"rescaled a 1M-point points3D.bin ({len(buf) / 1e6:.0f} MB) in {elapsed:.2f} s "
          f"({cpu:.2f} s CPU)")
    assert cpu < 8.0, f"rescaling 1M points took {cpu:.1f} s of CPU"  # CPU: load-independent


def test_scale_must_be_positive(binary_copy: Path, tmp_path: Path) -> None:
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="scale"):
            write_scaled_colmap_model(binary_copy, tmp_path / "x", bad)
    with pytest.raises(InputError, match="over its source"):
        write_scaled_colmap_model(binary_copy, binary_copy, 2.0)


# ----------------------------------------------------------------------------- errors


def _raises_naming(path_part: str, func, *args) -> InputError:  # type: ignore[no-untyped-def]
    with pytest.raises(InputError) as info:
        func(*args)
    assert path_part in str(info.value), str(info.value)
    assert "\n" not in str(info.value)
    return info.value


def test_folder_errors(tmp_path: Path) -> None:
    err = _raises_naming("nowhere", read_colmap_model, tmp_path / "nowhere")
    assert "not found" in str(err)
    (tmp_path / "file.txt").write_text("x")
    assert "not a folder" in str(_raises_naming("file.txt", read_colmap_model,
                                                tmp_path / "file.txt"))
    (tmp_path / "cameras.txt").write_text("# nothing\n")
    err = _raises_naming(str(tmp_path), read_colmap_model, tmp_path)
    assert "images.txt" in str(err) and "points3D.txt" in str(err)
    assert "cameras.txt" not in str(err).split("missing")[1]
    empty = tmp_path / "sparse"
    shutil.copytree(RECON, empty / "0")
    assert "'0'" in str(_raises_naming("sparse", read_colmap_model, empty))


def _truncate(path: Path, keep: int) -> None:
    path.write_bytes(path.read_bytes()[:keep])


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_or_padded_binary(binary_copy: Path, name: str) -> None:
    path = binary_copy / name
    data = path.read_bytes()
    rng = np.random.default_rng(3)
    cuts = {0, 4, 8, 9, len(data) - 1, *rng.integers(1, len(data), 25).tolist()}
    for cut in sorted(cuts):
        path.write_bytes(data[:cut])
        _raises_naming(name, read_colmap_model, binary_copy)
        if name != "cameras.bin":
            _raises_naming(name, write_scaled_colmap_model, binary_copy,
                           binary_copy.parent / "out", 2.0)
    path.write_bytes(data + b"\0\1")
    assert "unexpected bytes" in str(_raises_naming(name, read_colmap_model, binary_copy))


def test_count_larger_than_file(binary_copy: Path) -> None:
    path = binary_copy / "images.bin"
    data = path.read_bytes()
    path.write_bytes(struct.pack("<Q", 1000) + data[8:])
    err = _raises_naming("images.bin", read_colmap_model, binary_copy)
    assert "image" in str(err)
    path.write_bytes(struct.pack("<Q", 2**63) + data[8:])
    assert "1000" not in str(_raises_naming("images.bin", read_colmap_model, binary_copy))


def test_corrupt_binary_fields(binary_copy: Path) -> None:
    cams = binary_copy / "cameras.bin"
    data = bytearray(cams.read_bytes())
    data[12:16] = struct.pack("<i", 99)  # model id of the first camera
    cams.write_bytes(bytes(data))
    assert "model id 99" in str(_raises_naming("cameras.bin", read_colmap_model, binary_copy))
    data[12:16] = struct.pack("<i", 1)  # PINHOLE: 4 params where SIMPLE_PINHOLE wrote 3
    cams.write_bytes(bytes(data))
    _raises_naming("cameras.bin", read_colmap_model, binary_copy)
    data[12:16] = struct.pack("<i", 0)
    cams.write_bytes(bytes(data))
    pts = binary_copy / "points3D.bin"
    pdata = bytearray(pts.read_bytes())
    pdata[8 + 43:8 + 51] = struct.pack("<Q", 2**62)  # absurd track length
    pts.write_bytes(bytes(pdata))
    _raises_naming("points3D.bin", read_colmap_model, binary_copy)
    _raises_naming("points3D.bin", write_scaled_colmap_model, binary_copy,
                   binary_copy.parent / "o", 2.0)


def test_random_corruption_never_escapes(binary_copy: Path) -> None:
    """Flipped bytes either still parse or raise InputError, never another exception."""
    rng = np.random.default_rng(11)
    originals = {n: (binary_copy / n).read_bytes() for n in ("images.bin", "points3D.bin")}
    for _ in range(40):
        name = str(rng.choice(list(originals)))
        data = bytearray(originals[name])
        for pos in rng.integers(0, min(len(data), 4000), 3):
            data[pos] = int(rng.integers(0, 256))
        (binary_copy / name).write_bytes(bytes(data))
        try:
            read_colmap_model(binary_copy)
        except InputError as e:
            assert name in str(e) or "images.bin" in str(e)
        (binary_copy / name).write_bytes(originals[name])


def _edit_line(path: Path, lineno: int, new: bytes) -> None:
    lines = _split_lines(path)
    lines[lineno - 1] = new
    path.write_bytes(b"".join(lines))


def test_unparsable_text_lines_name_the_line(text_copy: Path) -> None:
    originals = {p.name: p.read_bytes() for p in text_copy.iterdir()}
    cases = [
        ("cameras.txt", 4, b"1 SIMPLE_PINHOLE 1919 1079 1847.53 959.5\n", "line 4"),
        ("cameras.txt", 4, b"1 SIMPLE_PINHOL 1919 1079 1847.53 959.5 539.5\n", "unknown"),
        ("cameras.txt", 4, b"1 SIMPLE_PINHOLE 1919 wide 1847.53 959.5 539.5\n", "line 4"),
        ("images.txt", 5, b"4 0.86 0.01 0.34 0.37 -7.9 -4.9 4.x 1 03.jpg\n", "line 5"),
        ("images.txt", 5, b"4 0.86 0.01 0.34\n", "line 5"),
        ("images.txt", 6, b"355.968 4.50115 -1 863.644 4.99844\n", "line 6"),
        ("images.txt", 6, b"355.968 4.50115 -1 863.644 4.99844 abc\n", "line 6"),
        ("images.txt", 6, b"355.968 4.50115 -7\n", "line 6"),
        ("points3D.txt", 5, b"708 -2.39675 4.62278 13.2759 57 57 49 0.32 2 4561 3\n", "line 5"),
        ("points3D.txt", 5, b"708 -2.39675 4.62278 13.2759 57 57 4x9 0.32 2 4561\n", "line 5"),
        ("points3D.txt", 5, b"708 -2.39675 nan? 13.2759 57 57 49 0.32 2 4561\n", "line 5"),
        ("points3D.txt", 5, b"708 -2.39675 4.6 13.2 57 57 49 0.32 2 -4561\n", "line 5"),
    ]
    for name, lineno, new, expect in cases:
        _edit_line(text_copy / name, lineno, new)
        err = _raises_naming(name, read_colmap_model, text_copy)
        assert expect in str(err)
        (text_copy / name).write_bytes(originals[name])
    _edit_line(text_copy / "images.txt", 5, b"4 0.86 0.01 0.34 0.37 -7.9 -4.9 4.x 1 03.jpg\n")
    err = _raises_naming("images.txt", write_scaled_colmap_model, text_copy,
                         text_copy.parent / "out", 2.0)
    assert "line 5" in str(err)


def test_consistency_errors(text_copy: Path) -> None:
    images = text_copy / "images.txt"
    original = images.read_bytes()
    _edit_line(images, 5, b"4 0.860298 0.0113506 0.344769 0.375358 -7.96 -4.99 4.36 2 03.jpg\n")
    assert "camera 2" in str(_raises_naming("images.txt", read_colmap_model, text_copy))
    images.write_bytes(original.replace(b" 1 00.jpg\n", b" 1 00.jpg\n", 1).replace(
        b"\n1 0.998245", b"\n4 0.998245"))
    assert "duplicate image id 4" in str(_raises_naming("images.txt", read_colmap_model,
                                                        text_copy))
    images.write_bytes(b"# no images\n")
    assert "no registered images" in str(_raises_naming("images.txt", read_colmap_model,
                                                        text_copy))
    images.write_bytes(original)
    points = text_copy / "points3D.txt"
    lines = _split_lines(points)
    assert lines[3].startswith(b"708 ")
    points.write_bytes(b"".join(lines[:3] + lines[4:]))  # drop point 708, still observed
    err = _raises_naming("images.txt", read_colmap_model, text_copy)
    assert "708" in str(err)


def test_binary_consistency_errors(binary_copy: Path, fixture_model: SparseModel) -> None:
    cams = dict(fixture_model.cameras)
    cams[2] = cams.pop(1)
    bad = SparseModel(cams, fixture_model.images, fixture_model.point3D_ids,
                      fixture_model.points_xyz)
    write_colmap_model_binary(bad, binary_copy)
    assert "camera 1" in str(_raises_naming("images.bin", read_colmap_model, binary_copy))
    empty = SparseModel(fixture_model.cameras, {}, np.zeros(0, np.uint64), np.zeros((0, 3)))
    write_colmap_model_binary(empty, binary_copy)
    _raises_naming("images.bin", read_colmap_model, binary_copy)
