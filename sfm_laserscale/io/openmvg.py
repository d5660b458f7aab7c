"""OpenMVG input and output: ``sfm_data.json`` read as a :class:`SparseModel` in COLMAP's
conventions (``read_openmvg_sfm_data``), SIFT regions read as COLMAP-ordered descriptors
(``openmvg_model_features``), a rescaled ``sfm_data.json`` (``write_scaled_openmvg_sfm_data``:
only the number tokens of the pose centres and 3D points change, every other byte is copied).

The file layout, the conversions (pixel origin +0.5 px, camera models, descriptor bin order,
RootSIFT) and the measurements behind them are in docs/OPENMVG.md.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import (
    INVALID_POINT3D_ID,
    Camera,
    Image,
    ImageFeatures,
    ObservationFeatures,
    Pose,
    SparseModel,
)

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: OpenMVG pixel coordinates + this = COLMAP pixel coordinates (docs/OPENMVG.md).
OPENMVG_TO_COLMAP_PX = 0.5
_UNDEFINED_INDEX = 2**32 - 1  # OpenMVG's UndefinedIndexT
_CEREAL_NEW = 0x80000000  # cereal: first occurrence of a polymorphic type / shared pointer
_CEREAL_ID_MASK = 0x7FFFFFFF
_CEREAL_BASE_TYPE = 0x40000000  # cereal: the pointer holds the base type itself (plain View)
_MATCH_TOL_PX = 0.02  # landmark x vs .feat keypoint (the .feat text may hold 6 digits)
_SIFT_DESCRIBERS = ("SIFT_Image_describer",)
_DESC_HEADER = 8  # uint64 descriptor count


# --------------------------------------------------------------------------- cameras


def _vlfeat_to_colmap_index() -> I64:
    """Column permutation: colmap_desc = vlfeat_desc[:, index] (orientation bins reversed)."""
    cells, bins = np.meshgrid(np.arange(16), np.arange(8), indexing="ij")
    return (8 * cells + (-bins) % 8).reshape(-1).astype(np.int64)


VLFEAT_TO_COLMAP = _vlfeat_to_colmap_index()


def _f_pp(d: dict[str, Any], two_focals: bool) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in COLMAP pixels from an OpenMVG pinhole record."""
    f = d["focal_length"]
    fx, fy = (float(f[0]), float(f[1])) if two_focals else (float(f), float(f))
    cx, cy = (float(v) for v in d["principal_point"])
    # OpenMVG principal point is in its pixel convention: +0.5 px to COLMAP's.
    return fx, fy, cx + OPENMVG_TO_COLMAP_PX, cy + OPENMVG_TO_COLMAP_PX


def _disto(d: dict[str, Any], key: str, n: int) -> list[float]:
    vals = [float(v) for v in d[key]]
    if len(vals) != n:
        raise ValueError(f"{key!r} must hold {n} numbers, found {len(vals)}")
    return vals


def _pinhole(d: dict[str, Any], two: bool = False) -> tuple[str, list[float]]:
    fx, fy, cx, cy = _f_pp(d, two)
    return "PINHOLE", [fx, fy, cx, cy]


def _radial_k1(d: dict[str, Any]) -> tuple[str, list[float]]:
    fx, _, cx, cy = _f_pp(d, False)
    return "SIMPLE_RADIAL", [fx, cx, cy, *_disto(d, "disto_k1", 1)]


def _radial_k3(d: dict[str, Any]) -> tuple[str, list[float]]:
    fx, fy, cx, cy = _f_pp(d, False)
    k1, k2, k3 = _disto(d, "disto_k3", 3)
    # FULL_OPENCV radial term (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶).
    return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, 0.0, 0.0, k3, 0.0, 0.0, 0.0]


def _brown(d: dict[str, Any], key: str = "disto_t2", two: bool = False) -> tuple[str, list[float]]:
    fx, fy, cx, cy = _f_pp(d, two)
    k1, k2, k3, t1, t2 = _disto(d, key, 5)
    return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, t1, t2, k3, 0.0, 0.0, 0.0]


def _fisheye(d: dict[str, Any]) -> tuple[str, list[float]]:
    fx, fy, cx, cy = _f_pp(d, False)
    return "OPENCV_FISHEYE", [fx, fy, cx, cy, *_disto(d, "fisheye", 4)]


def _fisheye1(d: dict[str, Any]) -> tuple[str, list[float]]:
    fx, fy, cx, cy = _f_pp(d, False)
    return "FOV", [fx, fy, cx, cy, *_disto(d, "fisheye1", 1)]


#: OpenMVG intrinsic type -> converter to (COLMAP model, params in COLMAP pixels).
INTRINSIC_CONVERTERS: dict[str, Callable[[dict[str, Any]], tuple[str, list[float]]]] = {
    "pinhole": _pinhole,
    "pinhole_radial_k1": _radial_k1,
    "pinhole_radial_k3": _radial_k3,
    "pinhole_brown_t2": _brown,
    "fisheye": _fisheye,
    "fisheye1": _fisheye1,
    "pinhole_2": lambda d: _pinhole(d, True),
    "pinhole_brown_t2_2": lambda d: _brown(d, "disto_t2_2", True),
}


# --------------------------------------------------------------------------- cereal helpers


def _flatten_bases(data: dict[str, Any]) -> dict[str, Any]:
    """Merge base-class fields that newer cereal nests under ``value0`` into one dict."""
    base = data.get("value0")
    if not isinstance(base, dict):
        return data
    merged = _flatten_bases(base)
    merged.update({k: v for k, v in data.items() if k != "value0"})
    return merged


class _Pointers:
    """cereal polymorphic shared pointers: type names and objects referenced again by id."""

    def __init__(self) -> None:
        self.names: dict[int, str] = {}
        self.objects: dict[int, dict[str, Any]] = {}

    def read(self, value: Any, where: str, path: Path) -> tuple[str | None, dict[str, Any]]:
        """(polymorphic type name, or None for an object of the base type; flattened data)."""
        try:
            name = self._type_name(int(value["polymorphic_id"]), value)
            wrapper = value["ptr_wrapper"]
            oid = int(wrapper["id"]) & _CEREAL_ID_MASK
            if "data" in wrapper:
                self.objects[oid] = _flatten_bases(dict(wrapper["data"]))
            data = self.objects[oid]  # no data: the same shared object again
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{where}: not an OpenMVG cereal object ({e!r})", path) from e
        return name, data

    def _type_name(self, pid: int, value: dict[str, Any]) -> str | None:
        if pid == _CEREAL_BASE_TYPE:
            return None
        if pid & _CEREAL_NEW:  # first object of this type: its name follows
            self.names[pid & _CEREAL_ID_MASK] = str(value["polymorphic_name"])
        return self.names[pid & _CEREAL_ID_MASK]


def _entries(doc: dict[str, Any], section: str, path: Path) -> list[tuple[int, Any]]:
    """(key, value) pairs of a cereal map section (missing section: empty)."""
    items = doc.get(section, [])
    if not isinstance(items, list):
        raise InputError(f"'{section}' must be a list of key/value entries", path)
    try:
        return [(int(e["key"]), e["value"]) for e in items]
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"'{section}': entry without an integer 'key' and a 'value' ({e!r})",
                         path) from e


# --------------------------------------------------------------------------- sfm_data parsing


@dataclass(frozen=True)
class OpenMVGView:
    """One registered view of an sfm_data (ids as in the file)."""

    view_id: int
    name: str  # local_path/filename (filename alone when local_path is empty)
    stem: str  # regions file stem (OpenMVG: file name without extension)
    intrinsic_id: int
    pose_id: int


@dataclass(frozen=True)
class OpenMVGScene:
    """What an sfm_data.json holds, in COLMAP conventions (pixels +0.5, cam_from_world)."""

    cameras: dict[int, Camera]
    views: dict[int, OpenMVGView]  # registered views only
    poses: dict[int, Pose]
    point3D_ids: NDArray[np.uint64]  # (M,) landmark ids
    points_xyz: F64  # (M, 3) model units
    obs_view: I64  # (K,) view id of each observation (registered views only)
    obs_feat: I64  # (K,) feature id (row of the view's .feat)
    obs_xy_px: F64  # (K, 2) COLMAP pixels
    obs_point: I64  # (K,) row in points_xyz


def _load_json(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise InputError("OpenMVG sfm_data not found", path)
    if not path.is_file():
        raise InputError("not a file (expected an OpenMVG sfm_data.json)", path)
    try:
        doc = json.loads(path.read_bytes())
    except json.JSONDecodeError as e:
        raise InputError(f"corrupt JSON: {e.msg} at line {e.lineno} column {e.colno}",
                         path) from e
    except (UnicodeDecodeError, OSError) as e:
        raise InputError(f"cannot read JSON: {e}", path) from e
    if not isinstance(doc, dict) or "views" not in doc or "sfm_data_version" not in doc:
        raise InputError("not an OpenMVG sfm_data file (no 'sfm_data_version' / 'views')", path)
    return doc


def _views(doc: dict[str, Any], ptrs: _Pointers, path: Path) -> dict[int, OpenMVGView]:
    """Every view of the file (registration is checked by the caller)."""
    views = {}
    for key, value in _entries(doc, "views", path):
        _, d = ptrs.read(value, f"views[key {key}]", path)
        try:
            filename, local = str(d["filename"]), str(d.get("local_path", "") or "")
            vid, iid, pid = int(d["id_view"]), int(d["id_intrinsic"]), int(d["id_pose"])
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"views[key {key}]: missing or bad field ({e!r})", path) from e
        name = f"{local.rstrip('/')}/{filename}" if local else filename
        views[vid] = OpenMVGView(vid, name, Path(filename).stem, iid, pid)
    return views


def _cameras(doc: dict[str, Any], ptrs: _Pointers, wanted: set[int],
             path: Path) -> dict[int, Camera]:
    """COLMAP cameras of the intrinsics used by registered views."""
    cameras = {}
    for key, value in _entries(doc, "intrinsics", path):
        name, d = ptrs.read(value, f"intrinsics[key {key}]", path)
        if key not in wanted:
            continue
        convert = INTRINSIC_CONVERTERS.get(name or "")
        if convert is None:
            raise InputError(
                f"intrinsic {key}: camera model {name!r} is not supported (supported: "
                f"{', '.join(INTRINSIC_CONVERTERS)})", path)
        try:
            model, params = convert(d)
            cameras[key] = Camera(key, model, int(d["width"]), int(d["height"]),
                                  np.asarray(params, dtype=np.float64))
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise InputError(f"intrinsic {key} ({name}): missing or bad field ({e!r})",
                             path) from e
    return cameras


def _poses(doc: dict[str, Any], path: Path) -> dict[int, Pose]:
    poses = {}
    for key, value in _entries(doc, "extrinsics", path):
        try:
            R = np.asarray(value["rotation"], dtype=np.float64).reshape(3, 3)
            C = np.asarray(value["center"], dtype=np.float64).reshape(3)
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"extrinsics[key {key}]: bad rotation/center ({e!r})", path) from e
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise InputError(f"extrinsics[key {key}]: rotation is not a rotation matrix", path)
        poses[key] = Pose(R, -R @ C)  # OpenMVG stores (R, C): t = −R C
    return poses


def _structure(doc: dict[str, Any], views: dict[int, OpenMVGView], path: Path) -> tuple[
        NDArray[np.uint64], F64, I64, I64, F64, I64]:
    """Landmarks and their observations in registered views (flattened)."""
    ids, xyz, o_view, o_feat, o_xy, o_pt = [], [], [], [], [], []
    for row, (key, value) in enumerate(_entries(doc, "structure", path)):
        try:
            xyz.append([float(v) for v in value["X"]])
            for ob in value["observations"]:
                vid = int(ob["key"])
                if vid in views:
                    o_view.append(vid)
                    o_feat.append(int(ob["value"]["id_feat"]))
                    o_xy.append([float(v) for v in ob["value"]["x"]])
                    o_pt.append(row)
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"structure[key {key}]: bad landmark ({e!r})", path) from e
        ids.append(key)
    try:  # ragged lists (a 2-number X) fail here, not above
        pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3) if xyz else np.zeros((0, 3))
        xy = np.asarray(o_xy, dtype=np.float64).reshape(-1, 2) if o_xy else np.zeros((0, 2))
    except ValueError:
        pts, xy = np.zeros((0, 3)), np.zeros((0, 2))
    if pts.shape[0] != len(ids) or xy.shape[0] != len(o_view):
        raise InputError("structure: every X must have 3 numbers and every x 2", path)
    return (np.asarray(ids, dtype=np.uint64), pts, np.asarray(o_view, dtype=np.int64),
            np.asarray(o_feat, dtype=np.int64), xy + OPENMVG_TO_COLMAP_PX,  # +0.5: COLMAP px
            np.asarray(o_pt, dtype=np.int64))


def parse_openmvg_sfm_data(path: str | Path) -> OpenMVGScene:
    """Cameras, registered views, poses and structure of an sfm_data.json (COLMAP conventions)."""
    p = Path(path)
    if p.suffix.lower() in (".bin", ".xml"):
        raise InputError(
            "only the JSON form of OpenMVG's sfm_data is read: convert it with "
            f"openMVG_main_ConvertSfM_DataFormat -i {p.name} -o sfm_data.json", p)
    doc = _load_json(p)
    poses = _poses(doc, p)
    ptrs = _Pointers()  # cereal numbers types and shared objects over the whole file
    all_views = _views(doc, ptrs, p)
    views = {k: v for k, v in all_views.items()
             if v.intrinsic_id != _UNDEFINED_INDEX and v.pose_id in poses}
    if len(views) < len(all_views):
        logger.info("%s: %d of %d views have no pose (not registered, left out)", p,
                    len(all_views) - len(views), len(all_views))
    if not views:
        raise InputError("no view has a pose: not a reconstruction (run an OpenMVG SfM "
                         "pipeline first, or give its output sfm_data)", p)
    cameras = _cameras(doc, ptrs, {v.intrinsic_id for v in views.values()}, p)
    missing = sorted({v.intrinsic_id for v in views.values()} - set(cameras))
    if missing:
        raise InputError(f"views use intrinsic id(s) {missing} that 'intrinsics' lacks", p)
    ids, xyz, o_view, o_feat, o_xy, o_pt = _structure(doc, views, p)
    if len(np.unique(ids)) != len(ids):
        raise InputError("structure: duplicate landmark ids", p)
    if np.any(o_feat < 0):
        raise InputError("structure: negative feature id in an observation", p)
    return OpenMVGScene(cameras, views, poses, ids, xyz, o_view, o_feat, o_xy, o_pt)


# --------------------------------------------------------------------------- regions


def find_openmvg_regions_dir(sfm_data_path: str | Path) -> Path | None:
    """``matches/`` beside the sfm_data, or beside its folder (OpenMVG pipeline layout)."""
    p = Path(sfm_data_path)
    for cand in (p.parent / "matches", p.parent.parent / "matches"):
        if cand.is_dir() and ((cand / "image_describer.json").is_file()
                              or next(cand.glob("*.feat"), None) is not None):
            return cand
    return None


def _describer(regions_dir: Path) -> bool:
    """Check image_describer.json is VLFeat SIFT; returns its ``root_sift`` flag."""
    path = regions_dir / "image_describer.json"
    if not path.is_file():
        raise InputError("OpenMVG image_describer.json not found (needed to know the "
                         "descriptor type)", path)
    try:
        doc = json.loads(path.read_bytes())
        desc = doc["image_describer"]
        name = str(desc.get("polymorphic_name", ""))
        data = _flatten_bases(desc["ptr_wrapper"]["data"])
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise InputError(f"corrupt OpenMVG image_describer.json ({e!r})", path) from e
    if name not in _SIFT_DESCRIBERS:
        raise InputError(
            f"regions of type {name!r} cannot be matched with COLMAP SIFT (only OpenMVG's "
            "VLFeat SIFT_Image_describer is supported): give --images to re-extract SIFT", path)
    return bool(data.get("params", {}).get("root_sift", True))


def _read_feat(path: Path) -> F64:
    """(N, 2) keypoints of a .feat file in COLMAP pixels."""
    if not path.is_file():
        raise InputError("OpenMVG regions file not found", path)
    try:
        rows = [line.split() for line in path.read_text(encoding="ascii").splitlines()]
        rows = [r for r in rows if r]
        ncol = {len(r) for r in rows}
        if len(ncol) > 1 or (ncol and min(ncol) < 2):
            raise ValueError(f"lines with {sorted(ncol)} values")
        xy = np.asarray(rows, dtype=np.float64).reshape(len(rows), -1)[:, :2]
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"corrupt .feat file (expected 'x y scale orientation' lines): {e}",
                         path) from e
    return xy + OPENMVG_TO_COLMAP_PX  # OpenMVG keypoints: +0.5 px to COLMAP's convention


def _read_desc(path: Path, n_expected: int) -> NDArray[np.uint8]:
    """(N, 128) uint8 descriptors of a .desc file (uint64 count, then N × 128 bytes)."""
    if not path.is_file():
        raise InputError("OpenMVG regions file not found", path)
    raw = path.read_bytes()
    if len(raw) < _DESC_HEADER:
        raise InputError("truncated .desc file (no descriptor count)", path)
    n = int(np.frombuffer(raw, "<u8", 1)[0])
    if len(raw) != _DESC_HEADER + 128 * n:
        raise InputError(f"corrupt .desc file: {n} SIFT descriptors need "
                         f"{_DESC_HEADER + 128 * n} bytes, the file has {len(raw)}", path)
    if n != n_expected:
        raise InputError(f".desc holds {n} descriptors but its .feat {n_expected} keypoints",
                         path)
    return np.frombuffer(raw, np.uint8, 128 * n, _DESC_HEADER).reshape(n, 128)


def openmvg_sift_to_colmap(desc: NDArray[np.uint8], root_sift: bool,
                           normalization: str = "L1_ROOT") -> NDArray[np.uint8]:
    """OpenMVG (VLFeat order, RootSIFT or L2 ×512) → COLMAP order and normalisation (uint8)."""
    if normalization not in ("L1_ROOT", "L2"):
        raise InputError(f"SIFT normalization: L1_ROOT or L2, not {normalization!r}")
    d = np.asarray(desc, dtype=np.uint8)[:, VLFEAT_TO_COLMAP]
    if root_sift == (normalization == "L1_ROOT"):
        return np.ascontiguousarray(d)
    v = d.astype(np.float64) + 0.5  # OpenMVG truncates: the midpoint of [x, x + 1) is unbiased
    if root_sift:  # RootSIFT → L2: square back to the L1-normalised histogram, L2-normalise
        v = v * v
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    else:  # L2 → RootSIFT, as COLMAP's L1_ROOT normalisation does it
        v = np.sqrt(v / np.maximum(v.sum(axis=1, keepdims=True), 1e-12))
    return np.clip(np.round(512.0 * v), 0, 255).astype(np.uint8)  # COLMAP's uint8 storage


def read_openmvg_regions(regions_dir: str | Path, stems: Iterable[str],
                         normalization: str = "L1_ROOT") -> dict[str, ImageFeatures]:
    """Regions stem -> every keypoint (COLMAP pixels) and SIFT descriptor (COLMAP order)."""
    folder = Path(regions_dir)
    if not folder.is_dir():
        raise InputError("OpenMVG regions folder not found", folder)
    root_sift = _describer(folder)
    out = {}
    for stem in stems:
        xy = _read_feat(folder / f"{stem}.feat")
        desc = _read_desc(folder / f"{stem}.desc", len(xy))
        out[stem] = ImageFeatures(xy, openmvg_sift_to_colmap(desc, root_sift, normalization))
    return out


# --------------------------------------------------------------------------- model


def _check_observed(scene: OpenMVGScene, view: OpenMVGView, sel: I64, kp: F64,
                    feat_file: Path) -> None:
    """Feature ids in range and landmark x equal to the .feat keypoint."""
    feats = scene.obs_feat[sel]
    if len(feats) and feats.max() >= len(kp):
        raise InputError(f"view {view.name!r}: observation of feature {feats.max()} but the "
                         f"file has {len(kp)} keypoints (regions of another run?)", feat_file)
    if len(feats):
        off = float(np.abs(kp[feats] - scene.obs_xy_px[sel]).max())
        if off > _MATCH_TOL_PX:
            raise InputError(f"view {view.name!r}: observations differ from their keypoints by "
                             f"up to {off:.3f} px (regions of another run?)", feat_file)


def _first_per_feature(feats: I64, view: OpenMVGView) -> NDArray[np.bool_]:
    """Mask keeping one observation per feature id (several landmarks on one is corrupt)."""
    _, first = np.unique(feats, return_index=True)
    keep = np.zeros(len(feats), dtype=bool)
    keep[first] = True
    if not keep.all():
        logger.warning("view %s: %d features observe several landmarks; the first is kept",
                       view.name, int((~keep).sum()))
    return keep


def _image(scene: OpenMVGScene, view: OpenMVGView, kp: F64 | None) -> Image:
    """One model image: every keypoint (kp given) or only its observations by feature id."""
    sel = np.flatnonzero(scene.obs_view == view.view_id)
    sel = sel[np.argsort(scene.obs_feat[sel], kind="stable")]
    sel = sel[_first_per_feature(scene.obs_feat[sel], view)]
    pid = scene.point3D_ids[scene.obs_point[sel]]
    if kp is None:
        xy, ids = scene.obs_xy_px[sel].copy(), pid.astype(np.uint64)
    else:
        xy = kp.copy()
        ids = np.full(len(kp), INVALID_POINT3D_ID, dtype=np.uint64)
        ids[scene.obs_feat[sel]] = pid
    return Image(view.view_id, view.name, view.intrinsic_id, scene.poses[view.pose_id], xy, ids)


def _view_keypoints(scene: OpenMVGScene, folder: Path) -> dict[int, F64]:
    """View id -> every keypoint of its .feat, checked against the view's observations."""
    out = {}
    for vid, view in scene.views.items():
        feat_file = folder / f"{view.stem}.feat"
        out[vid] = _read_feat(feat_file)
        _check_observed(scene, view, np.flatnonzero(scene.obs_view == vid), out[vid], feat_file)
    return out


def read_openmvg_sfm_data(path: str | Path, regions_dir: str | Path | None = None) -> SparseModel:
    """SparseModel (source_format "openmvg") of an sfm_data.json; see the module docstring.

    With regions (``regions_dir``; else looked for beside the file, and ignored with a
    warning if they do not fit), images hold every keypoint (keypoint i = observation i);
    without, only their observations.
    """
    p = Path(path)
    scene = parse_openmvg_sfm_data(p)
    folder = Path(regions_dir) if regions_dir is not None else find_openmvg_regions_dir(p)
    kps: dict[int, F64] = {}
    if folder is not None:
        try:
            kps = _view_keypoints(scene, folder)
        except InputError as e:
            if regions_dir is not None:
                raise
            logger.warning("%s: the regions found in %s do not fit (%s); the model's images "
                           "hold only their observations", p, folder, e)
            folder = None
    images = {vid: _image(scene, view, kps.get(vid)) for vid, view in sorted(scene.views.items())}
    logger.info("%s: %d registered views, %d landmarks%s", p, len(images), len(scene.point3D_ids),
                "" if folder is None else f", keypoints from {folder}")
    return SparseModel(scene.cameras, images, scene.point3D_ids.copy(), scene.points_xyz.copy(),
                       source_format="openmvg")


def openmvg_regions_are_sift(regions_dir: str | Path) -> bool:
    """True when the regions are OpenMVG's VLFeat SIFT (usable as COLMAP SIFT)."""
    try:
        _describer(Path(regions_dir))
    except InputError:
        return False
    return True


def openmvg_model_features(
    model: SparseModel, sfm_data_path: str | Path, regions_dir: str | Path,
    normalization: str = "L1_ROOT",
) -> dict[str, ImageFeatures] | dict[str, ObservationFeatures]:
    """Descriptors of the model's images from OpenMVG regions, aligned with ``Image.xy_px``.

    ``ImageFeatures`` when the model holds every keypoint of these regions (read with them),
    else ``ObservationFeatures`` of its observations (located through their feature ids).
    """
    folder = Path(regions_dir)
    scene = parse_openmvg_sfm_data(sfm_data_path)
    by_name = {v.name: v for v in scene.views.values()}
    images = [im for im in model.images.values() if im.name in by_name]
    regions = read_openmvg_regions(folder, {by_name[im.name].stem for im in images},
                                   normalization)
    full: dict[str, ImageFeatures] = {}
    tied: dict[str, ObservationFeatures] = {}
    for image in images:
        view = by_name[image.name]
        feats = regions[view.stem]
        if len(feats.xy_px) == len(image.xy_px) and (
                len(image.xy_px) == 0 or np.abs(feats.xy_px - image.xy_px).max() <= 0.05):
            full[image.name] = feats
            n = len(feats.xy_px)
            tied[image.name] = ObservationFeatures(np.arange(n, dtype=np.int64),
                                                   feats.descriptors, np.zeros(n))
        else:
            tied[image.name] = _tie_by_feature_id(scene, view, image, feats, folder)
    return full if len(full) == len(images) else tied


def _tie_by_feature_id(scene: OpenMVGScene, view: OpenMVGView, image: Image,
                       feats: ImageFeatures, folder: Path) -> ObservationFeatures:
    """ObservationFeatures of an observation-layout image: row i ↔ i-th observed feature."""
    feat_file = folder / f"{view.stem}.feat"
    sel = np.flatnonzero(scene.obs_view == view.view_id)
    _check_observed(scene, view, sel, feats.xy_px, feat_file)
    sel = sel[np.argsort(scene.obs_feat[sel], kind="stable")]
    feat_ids = scene.obs_feat[sel][_first_per_feature(scene.obs_feat[sel], view)]
    if len(feat_ids) != len(image.xy_px):
        raise InputError(
            f"image {image.name!r} of the model has {len(image.xy_px)} keypoints/observations "
            f"but these regions {len(feats.xy_px)} keypoints and the sfm_data {len(feat_ids)} "
            "observations (regions of another run?)", feat_file)
    dist = np.linalg.norm(feats.xy_px[feat_ids] - image.xy_px, axis=1)
    if len(dist) and dist.max() > 0.05:
        raise InputError(f"view {view.name!r}: the model's observations are not these "
                         "regions' keypoints (regions of another run?)", feat_file)
    return ObservationFeatures(np.arange(len(feat_ids), dtype=np.int64),
                               feats.descriptors[feat_ids].copy(), dist)


# --------------------------------------------------------------------------- rescaled output


_WS = re.compile(r"[ \t\n\r]*")
_NUM = r"(-?(?:0|[1-9]\d*)(?:\.\d+)?(?:[eE][+-]?\d+)?)"
_DECODER = json.JSONDecoder()
_SCALED_FIELDS = {"extrinsics": "center", "structure": "X", "control_points": "X"}


def _skip(text: str, i: int) -> int:
    m = _WS.match(text, i)
    return i if m is None else m.end()


def _expect(text: str, i: int, char: str) -> int:
    if i >= len(text) or text[i] != char:
        raise ValueError(f"expected {char!r} at character {i}")
    return i + 1


def _members(text: str, i: int) -> Iterator[tuple[str, int, int, Any]]:
    """(key, value start, value end, value) of the JSON object at ``text[i]`` (C parser)."""
    i = _skip(text, _expect(text, i, "{"))
    if text.startswith("}", i):
        return
    while True:
        key, i = _DECODER.raw_decode(text, i)
        i = _skip(text, _expect(text, _skip(text, i), ":"))
        value, end = _DECODER.raw_decode(text, i)
        yield str(key), i, end, value
        i = _skip(text, end)
        if text.startswith("}", i):
            return
        i = _skip(text, _expect(text, i, ","))


def _items(text: str, i: int) -> Iterator[tuple[int, int]]:
    """(start, end) of each value of the JSON array at ``text[i]``."""
    i = _skip(text, _expect(text, i, "["))
    if text.startswith("]", i):
        return
    while True:
        _, end = _DECODER.raw_decode(text, i)
        yield i, end
        i = _skip(text, end)
        if text.startswith("]", i):
            return
        i = _skip(text, _expect(text, i, ","))


def _member(text: str, i: int, key: str) -> tuple[int, int] | None:
    for k, start, end, _ in _members(text, i):
        if k == key:
            return start, end
    return None


def _exact_spans(text: str, start: int, section: str, field: str) -> list[tuple[int, int]]:
    """Spans of ``entry.value.<field>`` numbers, walking every entry (exact, slower)."""
    spans: list[tuple[int, int]] = []
    for s, _ in _items(text, start):
        value = _member(text, s, "value")
        where = None if value is None else _member(text, value[0], field)
        if where is None:
            raise ValueError(f"'{section}' entry at character {s} has no value.{field}")
        items = list(_items(text, where[0]))
        if len(items) != 3 or not all(isinstance(json.loads(text[a:b]), int | float)
                                      for a, b in items):
            raise ValueError(f"'{section}' entry at character {s}: {field} is not 3 numbers")
        spans += items
    return spans


def _fast_spans(text: str, start: int, end: int, field: str,
                entries: Any) -> list[tuple[int, int]] | None:
    """The same spans by one regex over the section, or None unless they provably agree
    with the parsed entries (same count, same values in the same order)."""
    pattern = re.compile(rf'"{field}"\s*:\s*\[\s*{_NUM}\s*,\s*{_NUM}\s*,\s*{_NUM}\s*\]')
    found = list(pattern.finditer(text, start, end))
    try:
        want = np.array([e["value"][field] for e in entries], dtype=np.float64).reshape(-1, 3)
    except (KeyError, TypeError, ValueError):
        return None
    got = np.array([[float(m.group(k)) for k in (1, 2, 3)] for m in found]).reshape(-1, 3)
    if got.shape != want.shape or not np.array_equal(got, want):
        return None
    return [m.span(k) for m in found for k in (1, 2, 3)]


def _scaled_spans(text: str) -> list[tuple[int, int]]:
    """Text spans of every pose centre and landmark X coordinate (in file order)."""
    spans: list[tuple[int, int]] = []
    keys = set()
    for key, start, end, value in _members(text, _skip(text, 0)):
        keys.add(key)
        field = _SCALED_FIELDS.get(key)
        if field is None:
            continue
        fast = _fast_spans(text, start, end, field, value)
        spans += fast if fast is not None else _exact_spans(text, start, key, field)
    if not {"sfm_data_version", "views"} <= keys:
        raise ValueError("not an OpenMVG sfm_data file (no 'sfm_data_version' / 'views')")
    return spans


def write_scaled_openmvg_sfm_data(src_json: str | Path, dst_json: str | Path,
                                  scale: float) -> Path:
    """Copy of an sfm_data.json with pose centres and landmark X (structure, control points)
    multiplied by ``scale``; every other byte of the file is kept as it is."""
    src, dst = Path(src_json), Path(dst_json)
    if not np.isfinite(scale) or scale <= 0:
        raise InputError(f"scale must be a positive finite number, got {scale}")
    if src.suffix.lower() in (".bin", ".xml"):
        raise InputError("only the JSON form of OpenMVG's sfm_data is rescaled", src)
    if not src.is_file():
        raise InputError("OpenMVG sfm_data not found", src)
    if dst.exists() and dst.resolve() == src.resolve():
        raise InputError("refusing to overwrite the input sfm_data", dst)
    try:
        text = src.read_bytes().decode("utf-8")
        spans = _scaled_spans(text)  # parses the whole file once (C parser)
    except json.JSONDecodeError as e:
        raise InputError(f"corrupt JSON: {e.msg} at line {e.lineno} column {e.colno}",
                         src) from e
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"unexpected sfm_data content: {e}", src) from e
    parts, last = [], 0
    for start, end in spans:
        old = float(text[start:end])
        new = old * float(scale)
        # repr: shortest text that reads back to the same double (cereal writes 17 digits);
        # a value that does not change keeps its text (scale 1 copies the file byte for byte).
        parts += [text[last:start], text[start:end] if new == old else repr(new)]
        last = end
    parts.append(text[last:])
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes("".join(parts).encode("utf-8"))
    logger.info("rescaled sfm_data (×%.9g, %d numbers) written to %s", scale, len(spans), dst)
    return dst


__all__ = [
    "INTRINSIC_CONVERTERS",
    "OPENMVG_TO_COLMAP_PX",
    "VLFEAT_TO_COLMAP",
    "OpenMVGScene",
    "OpenMVGView",
    "find_openmvg_regions_dir",
    "openmvg_model_features",
    "openmvg_regions_are_sift",
    "openmvg_sift_to_colmap",
    "parse_openmvg_sfm_data",
    "read_openmvg_regions",
    "read_openmvg_sfm_data",
    "write_scaled_openmvg_sfm_data",
]
