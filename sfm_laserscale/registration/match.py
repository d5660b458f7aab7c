"""2D–3D matches of a query image's descriptors against the model's descriptor index: Lowe's
ratio test with the second neighbour taken from another 3D point, one match per 3D point."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import ImageFeatures
from sfm_laserscale.registration.index import DescriptorIndex, _knn
from sfm_laserscale.registration.options import DESCRIPTOR_DIM, MatchOptions, RegistrationOptions


@dataclass(frozen=True)
class Matches:
    """2D–3D matches: one per 3D point, the best by descriptor distance."""

    query_idx: NDArray[np.int64]  # (n,) keypoint index in the query ImageFeatures
    point_rows: NDArray[np.int64]  # (n,) row in DescriptorIndex.points_xyz
    distance: NDArray[np.float32]  # (n,) L2 descriptor distance (uint8 units)

    def __len__(self) -> int:
        return int(len(self.query_idx))


def match_to_model(
    query: ImageFeatures, index: DescriptorIndex, options: MatchOptions | RegistrationOptions
) -> Matches:
    """Ratio-test matches (second neighbour from another 3D point), one per 3D point."""
    if isinstance(options, RegistrationOptions):
        options = options.match
    q = np.asarray(query.descriptors)
    if q.ndim != 2 or q.shape[1] != DESCRIPTOR_DIM:
        raise InputError(f"query descriptors must be (N, 128), got {q.shape}")
    empty = Matches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
    if len(q) == 0 or index.num_descriptors < 2:
        return empty
    # k > max descriptors of one point guarantees a neighbour from another point when
    # the pool allows; otherwise the k-th distance is a lower bound of that distance,
    # which keeps the test conservative.
    k = int(min(index.num_descriptors, np.bincount(index.point_rows).max() + 1))
    idx, dist = _knn(index, np.ascontiguousarray(q, dtype=np.float32), k)
    prow = index.point_rows[idx]
    other = prow != prow[:, :1]
    j2 = np.where(other.any(axis=1), other.argmax(axis=1), k - 1)
    d1, d2 = dist[:, 0], dist[np.arange(len(dist)), j2]
    ok = d1 < options.ratio * d2
    if options.max_distance is not None:
        ok &= d1 <= options.max_distance
    qi = np.flatnonzero(ok)
    if len(qi) == 0:
        return empty
    order = qi[np.argsort(d1[qi], kind="stable")]
    _, first = np.unique(prow[order, 0], return_index=True)  # best match per 3D point
    sel = np.sort(order[first])
    return Matches(query_idx=sel.astype(np.int64), point_rows=prow[sel, 0].astype(np.int64),
                   distance=d1[sel].astype(np.float32))
