"""Camera model of the underwater generator: pinhole + radial/tangential distortion.

The model is COLMAP's ``OPENCV`` (parameters ``fx fy cx cy k1 k2 p1 p2``), written here from
its equations (nothing is imported from the rest of the package). A camera-frame point
(x right, y down, z forward, metres) projects to normalised coordinates ``(u, v) = (x/z, y/z)``,
which are distorted::

    r2 = u² + v²,  radial = 1 + k1·r2 + k2·r2²
    ud = u·radial + 2·p1·u·v + p2·(r2 + 2·u²)
    vd = v·radial + p1·(r2 + 2·v²) + 2·p2·u·v

and mapped to pixels ``x_px = fx·ud + cx``, ``y_px = fy·vd + cy``. Pixel convention (COLMAP):
the centre of the top-left pixel is (0.5, 0.5), i.e. pixel (row i, column j) covers
x in [j, j+1), y in [i, i+1). Unprojection inverts the distortion by Newton iteration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
#: Newton iterations of the undistortion (converges in 3-5 for |k1| <= 0.2 inside the image)
UNDISTORT_ITERATIONS = 12


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics in pixels (COLMAP OPENCV model, COLMAP pixel convention)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def focal_px(self) -> float:
        """Mean focal length (pixels)."""
        return 0.5 * (self.fx + self.fy)


def distort_normalized(u: F64, v: F64, cam: CameraModel) -> tuple[F64, F64]:
    """Undistorted normalised coordinates -> distorted normalised coordinates."""
    r2 = u * u + v * v
    radial = 1.0 + cam.k1 * r2 + cam.k2 * r2 * r2
    ud = u * radial + 2.0 * cam.p1 * u * v + cam.p2 * (r2 + 2.0 * u * u)
    vd = v * radial + cam.p1 * (r2 + 2.0 * v * v) + 2.0 * cam.p2 * u * v
    return ud, vd


def _distortion_jacobian(u: F64, v: F64, cam: CameraModel) -> tuple[F64, F64, F64, F64]:
    """Partial derivatives (dud/du, dud/dv, dvd/du, dvd/dv) of :func:`distort_normalized`."""
    r2 = u * u + v * v
    radial = 1.0 + cam.k1 * r2 + cam.k2 * r2 * r2
    dradial = 2.0 * cam.k1 + 4.0 * cam.k2 * r2  # d(radial)/d(r2) * 2
    a = radial + u * u * dradial + 2.0 * cam.p1 * v + 6.0 * cam.p2 * u
    b = u * v * dradial + 2.0 * cam.p1 * u + 2.0 * cam.p2 * v
    c = u * v * dradial + 2.0 * cam.p1 * u + 2.0 * cam.p2 * v
    d = radial + v * v * dradial + 6.0 * cam.p1 * v + 2.0 * cam.p2 * u
    return a, b, c, d


def undistort_normalized(ud: F64, vd: F64, cam: CameraModel) -> tuple[F64, F64]:
    """Distorted -> undistorted normalised coordinates (Newton's method on the 2x2 system)."""
    u = np.array(ud, dtype=np.float64, copy=True)
    v = np.array(vd, dtype=np.float64, copy=True)
    for _ in range(UNDISTORT_ITERATIONS):
        fu, fv = distort_normalized(u, v, cam)
        ru, rv = fu - ud, fv - vd
        a, b, c, d = _distortion_jacobian(u, v, cam)
        det = a * d - b * c
        u -= (d * ru - b * rv) / det
        v -= (a * rv - c * ru) / det
        if float(np.max(np.abs(ru), initial=0.0) + np.max(np.abs(rv), initial=0.0)) < 1e-15:
            break
    return u, v


def project_px(xyz_cam_m: F64, cam: CameraModel) -> F64:
    """(N, 3) camera-frame points (metres, z > 0) -> (N, 2) COLMAP pixel coordinates."""
    pts = np.atleast_2d(np.asarray(xyz_cam_m, dtype=np.float64))
    u = pts[:, 0] / pts[:, 2]
    v = pts[:, 1] / pts[:, 2]
    ud, vd = distort_normalized(u, v, cam)
    return np.column_stack([cam.fx * ud + cam.cx, cam.fy * vd + cam.cy])


def unproject_px(xy_px: F64, cam: CameraModel) -> F64:
    """(N, 2) COLMAP pixel coordinates -> (N, 3) camera-frame rays with z = 1 (not unit)."""
    xy = np.atleast_2d(np.asarray(xy_px, dtype=np.float64))
    ud = (xy[:, 0] - cam.cx) / cam.fx
    vd = (xy[:, 1] - cam.cy) / cam.fy
    u, v = undistort_normalized(ud, vd, cam)
    return np.column_stack([u, v, np.ones_like(u)])


def colmap_camera_spec(cam: CameraModel) -> str:
    """The camera as COLMAP's ``OPENCV W H fx fy cx cy k1 k2 p1 p2`` string (full precision)."""
    params = (cam.fx, cam.fy, cam.cx, cam.cy, cam.k1, cam.k2, cam.p1, cam.p2)
    return f"OPENCV {cam.width} {cam.height} " + " ".join(repr(float(p)) for p in params)


def random_camera(rng: np.random.Generator, width: int, height: int) -> CameraModel:
    """A plausible ROV camera of this size: focal length from the sensor class (f ≈ 0.8 W for
    1920-wide video, f ≈ 0.8 W for 4000-wide stills, scaled for other sizes), principal point
    within 1 % of the centre, mild barrel distortion (k1 in [-0.15, -0.05])."""
    f_px = float(rng.uniform(0.755, 0.885)) * width  # 1450-1700 at 1920; 3020-3540 at 4000
    if width >= 3000:
        f_px = float(rng.uniform(3000.0, 3400.0)) * width / 4000.0
    aspect = float(rng.uniform(0.998, 1.002))
    return CameraModel(
        width=width,
        height=height,
        fx=f_px,
        fy=f_px * aspect,
        cx=0.5 * width + float(rng.uniform(-0.01, 0.01)) * width,
        cy=0.5 * height + float(rng.uniform(-0.01, 0.01)) * height,
        k1=float(rng.uniform(-0.15, -0.05)),
        k2=float(rng.uniform(0.0, 0.03)),
        p1=float(rng.uniform(-4e-4, 4e-4)),
        p2=float(rng.uniform(-4e-4, 4e-4)),
    )


def pixel_centres_px(x0: int, y0: int, w: int, h: int, supersample: int = 1) -> tuple[F64, F64]:
    """COLMAP coordinates of the sample points of the pixel block [x0, x0+w) × [y0, y0+h).

    With ``supersample`` = S each pixel holds S×S evenly spaced samples (cell midpoints); the
    result has shape (h·S, w·S) and pixel (i, j) owns samples [i·S:(i+1)·S, j·S:(j+1)·S].
    """
    s = int(supersample)
    xs = x0 + (np.arange(w * s, dtype=np.float64) + 0.5) / s
    ys = y0 + (np.arange(h * s, dtype=np.float64) + 0.5) / s
    gx, gy = np.meshgrid(xs, ys)
    return gx, gy


def bin_supersamples(values: NDArray[np.floating], supersample: int) -> F64:
    """Mean of each S×S block of a supersampled (h·S, w·S) array -> (h, w) pixel values."""
    s = int(supersample)
    h, w = values.shape[0] // s, values.shape[1] // s
    return np.asarray(values, np.float64).reshape(h, s, w, s).mean(axis=(1, 3))
