"""The metric scene carried into the frame of a reconstruction that is NOT a similarity of the
world (an SfM model with its own error, e.g. a wrong focal length): the mesh an MVS pipeline
would build from that model.

Each model point is triangulated in the world from its observations with the TRUE poses and
camera (linear least squares); a smooth map world -> model (a polynomial of degree ``degree``
in the three coordinates, fitted to those pairs by least squares) then carries the mesh's
vertices into the model frame. Used by the demo data set when its SfM is run with a wrong focal
length (``DemoDataOptions.sfm_focal_error``); shares no code with the estimators.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations_with_replacement

import numpy as np
import pycolmap
from numpy.typing import NDArray

from sfm_laserscale.model import Camera, Pose

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ModelWarp:
    """world (metres) -> model (units) polynomial map and its fit residual."""

    coefficients: F64  # (n_terms, 3)
    centre: F64  # (3,) world centre of the fit (metres)
    spread: float  # normalisation of the coordinates (metres)
    degree: int
    rms_model: float  # RMS residual of the fit, model units
    n_points: int

    def apply(self, xyz_world: F64) -> F64:
        """(N, 3) world metres -> (N, 3) model units."""
        return np.asarray(_monomials((np.atleast_2d(xyz_world) - self.centre) / self.spread,
                                     self.degree) @ self.coefficients, dtype=np.float64)


def _monomials(x: F64, degree: int) -> F64:
    """(N, n_terms) all monomials of the 3 coordinates up to ``degree`` (1 first)."""
    cols = [np.ones(len(x))]
    for d in range(1, degree + 1):
        for combo in combinations_with_replacement(range(3), d):
            cols.append(np.prod(x[:, list(combo)], axis=1))
    return np.column_stack(cols)


def triangulate(camera: Camera, poses: list[Pose], xy: list[F64]) -> F64:
    """The world point (3,) seen at pixels xy[i] from poses[i] (linear least squares)."""
    rows, rhs = [], []
    for pose, p in zip(poses, xy, strict=True):
        ray = camera.unproject(np.asarray(p, dtype=np.float64).reshape(1, 2))[0]
        # X_cam = R X + t ∥ ray: [ray]× (R X + t) = 0
        cross = np.array([[0.0, -ray[2], ray[1]], [ray[2], 0.0, -ray[0]],
                          [-ray[1], ray[0], 0.0]])
        rows.append(cross @ pose.R)
        rhs.append(-cross @ pose.t)
    a, b = np.vstack(rows), np.concatenate(rhs)
    return np.asarray(np.linalg.lstsq(a, b, rcond=None)[0], dtype=np.float64)


def fit_model_warp(rec: pycolmap.Reconstruction, true_camera: Camera,
                   true_poses: dict[str, Pose], degree: int = 2) -> ModelWarp:
    """The world -> model map of a reconstruction from its points triangulated in the world."""
    world, model = [], []
    for point in rec.points3D.values():
        poses, xy = [], []
        for el in point.track.elements:
            image = rec.images[el.image_id]
            if image.name in true_poses:
                poses.append(true_poses[image.name])
                xy.append(np.asarray(image.points2D[el.point2D_idx].xy, dtype=np.float64))
        if len(poses) >= 2:
            world.append(triangulate(true_camera, poses, xy))
            model.append(np.asarray(point.xyz, dtype=np.float64))
    w, m = np.array(world), np.array(model)
    centre = w.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((w - centre) ** 2, axis=1))))
    a = _monomials((w - centre) / spread, degree)
    coef = np.linalg.lstsq(a, m, rcond=None)[0]
    res = np.linalg.norm(a @ coef - m, axis=1)
    return ModelWarp(np.asarray(coef, dtype=np.float64), centre, spread, degree,
                     float(np.sqrt(np.mean(res**2))), len(w))
