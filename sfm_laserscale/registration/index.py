"""Descriptor index of a model's 3D points: exact search for small pools, else a FAISS inverted
file built in three passes over the features, one image at a time (docs/REGISTRATION.md).

``select_index_candidates`` then ``build_index`` (or ``build_descriptor_index`` for both) index
the descriptors of every observation with a 3D point; ``match.match_to_model`` searches it.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import faiss
import numpy as np
from numpy.typing import NDArray

from sfm_laserscale.errors import InputError
from sfm_laserscale.memory import trim_heap
from sfm_laserscale.model import (
    INVALID_POINT3D_ID,
    Image,
    ImageFeatures,
    ObservationFeatures,
    SparseModel,
)
from sfm_laserscale.registration.options import DESCRIPTOR_DIM, IndexOptions, RegistrationOptions
from sfm_laserscale.registration.ties import _point_rows

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class DescriptorIndex:
    """Descriptors of the model's 3D points, searchable by nearest neighbour."""

    descriptors: NDArray[np.uint8]  # (P, 128) for exact search; (0, 128) when the IVF holds them
    point_rows: NDArray[np.int32]  # (P,) row of each descriptor's point in points_xyz
    points_xyz: F64  # (M, 3) the model's points, model units
    point3D_ids: NDArray[np.uint64]  # noqa: N815 (COLMAP's name) (M,)
    method: str  # "ivf" | "exact"
    ivf_lists: int = 0  # k-means cells of the IVF (0 for exact search)
    ivf_probe: int = 0  # cells searched per query (0 for exact search)
    _searcher: Any = field(default=None, repr=False, compare=False)
    _storage: Any = field(default=None, repr=False, compare=False)  # memory of the IVF's lists

    @property
    def num_descriptors(self) -> int:
        """Number of descriptors in the pool."""
        return int(len(self.point_rows))

    @property
    def num_points(self) -> int:
        """Number of distinct 3D points with at least one descriptor."""
        return int(np.count_nonzero(np.bincount(self.point_rows)))


def _as_rows(desc: NDArray[Any]) -> NDArray[Any] | None:
    """(N,) view of (N, 128) uint8 descriptors as one 128-byte item per row, or None.

    Gathering such items is 3-4x faster than numpy's row-wise fancy indexing of the 2-D
    array (0.2 s instead of 0.8 s for 2M rows in random order).
    """
    if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_DIM:
        return None
    return np.ascontiguousarray(desc).view(np.dtype((np.void, DESCRIPTOR_DIM)))[:, 0]


def _rows_of(desc: NDArray[Any], which: NDArray[Any]) -> NDArray[np.uint8]:
    """``desc[which]`` as (M, 128) uint8, for an index or mask array (see ``_as_rows``)."""
    rows = _as_rows(desc)
    if rows is None:
        return np.asarray(desc[which], dtype=np.uint8)
    return rows[which].view(np.uint8).reshape(-1, DESCRIPTOR_DIM)


def _image_selection(
    model: SparseModel, name: str, image: Image, feats: ImageFeatures | ObservationFeatures,
    order: NDArray[np.int64] | None = None,
) -> tuple[NDArray[Any], NDArray[np.bool_], NDArray[np.int64]]:
    """(all descriptors, mask of those with a 3D point, their point rows) of one image."""
    if isinstance(feats, ObservationFeatures):
        obs_idx, desc = np.asarray(feats.observation_idx), np.asarray(feats.descriptors)
        if len(obs_idx) and (obs_idx.min() < 0 or obs_idx.max() >= len(image.xy_px)):
            raise InputError("tied observation index out of range for this image", path=name)
    else:
        desc = np.asarray(feats.descriptors)
        obs_idx = np.arange(len(desc))
        _check_aligned(name, image, feats)
    if desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_DIM or len(desc) != len(obs_idx):
        raise InputError(f"descriptors must be (N, 128), got {desc.shape}", path=name)
    ids = np.asarray(image.point3D_ids, dtype=np.uint64)[obs_idx]
    rows = _point_rows(model, ids, order)  # invalid / removed points -> -1
    ok = rows >= 0
    return desc, ok, rows[ok]


def _check_aligned(name: str, image: Image, feats: ImageFeatures) -> None:
    """Database convention: keypoint i of an image is observation i of the model."""
    if len(feats.xy_px) != len(image.xy_px) or len(feats.descriptors) != len(image.xy_px):
        raise InputError(
            f"{len(feats.xy_px)} keypoints but the model has {len(image.xy_px)} observations "
            "of this image (keypoint i must be observation i): wrong database for this model?",
            path=name,
        )
    if len(image.xy_px):
        offset = float(np.max(np.abs(np.asarray(feats.xy_px) - np.asarray(image.xy_px))))
        if offset > 0.05:
            raise InputError(
                f"keypoints differ from the model's observations by up to {offset:.2f} px: "
                "wrong database for this model?", path=name,
            )


# The pool is built in three passes over the features, so that a lazy mapping (the COLMAP
# database read one image at a time, ``io.colmap_database.open_database_features``) never
# holds more than one image's features beside the index (2M descriptors: 0.27 GB, where the
# features, a gathered pool and FAISS's own lists used to be held two at a time):
#   1. selection: each image's descriptors with a 3D point (alignment checked), and a random
#      training sample for the IVF's k-means (``_select``);
#   2. the descriptors of points seen more than ``max_descriptors_per_point`` times (ranked to
#      keep that many) and every candidate's IVF cell (``_rank_and_cells``);
#   3. every kept descriptor copied once, straight to its final place: the exact pool, or its
#      cell's list inside one buffer that FAISS reads without copying (``_IvfLayout``).


@dataclass(frozen=True)
class _Selection:
    """Pass 1: the candidate descriptors of each image (those of a 3D point).

    int32 rows (half the memory of int64 at 2M descriptors): models of < 2³¹ points."""

    names: tuple[str, ...]
    used: tuple[NDArray[np.int32], ...]  # per image: rows of its descriptors that are candidates
    sizes: tuple[int, ...]  # per image: its number of descriptor rows (checked on later passes)
    point_rows: NDArray[np.int32]  # (N,) point row of every candidate, images concatenated

    @property
    def starts(self) -> NDArray[np.int64]:
        """(images + 1,) offset of each image's candidates in ``point_rows``."""
        return np.r_[0, np.cumsum([len(u) for u in self.used])].astype(np.int64)


def _rank_per_point(
    desc: NDArray[np.float32], rows: NDArray[np.integer[Any]], max_per_point: int
) -> NDArray[np.int64]:
    """Indices keeping, per point, the ``max_per_point`` descriptors nearest its mean."""
    order = np.argsort(rows, kind="stable")
    r = rows[order]
    starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]])
    counts = np.diff(np.r_[starts, len(r)])
    means = np.add.reduceat(desc[order], starts, axis=0) / counts[:, None]
    group = np.repeat(np.arange(len(starts)), counts)
    dist = np.linalg.norm(desc[order] - means[group], axis=1)
    by_dist = np.lexsort((dist, group))  # within each group, nearest to the mean first
    rank = np.empty(len(r), dtype=np.int64)
    rank[by_dist] = np.arange(len(r)) - starts[group[by_dist]]
    return np.sort(order[rank < max_per_point])


@dataclass(frozen=True)
class DescriptorPool:
    """The descriptors to index: (P, 128) uint8 and the row of each one's 3D point."""

    descriptors: NDArray[np.uint8]
    point_rows: NDArray[np.int64]


def _ivf_lists(pool_size: int, options: IndexOptions) -> int:
    """Number of k-means cells of the IVF over a pool of this size."""
    nlist = options.ivf_lists or int(np.clip(round(np.sqrt(pool_size)), 16, 4096))
    return max(1, min(nlist, pool_size))


def _train_probability(model: SparseModel, names: Sequence[str], options: IndexOptions) -> float:
    """Probability of drawing each candidate into the k-means sample (pass 1).

    Drawn from an upper bound of the candidates (the observations with a point id), 1.5×
    the largest sample the IVF may need, so that at least that many are drawn (then cut down).
    """
    by_name = {im.name: im for im in model.images.values()}
    upper = sum(int(np.count_nonzero(np.asarray(by_name[n].point3D_ids, dtype=np.uint64)
                                     != INVALID_POINT3D_ID)) for n in names if n in by_name)
    if upper == 0 or _use_exact(upper, options):
        return 0.0
    wanted = _ivf_lists(upper, options) * max(1, options.train_per_list)
    return min(1.0, 1.5 * wanted / upper)


def _select(
    model: SparseModel, features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    train_p: float, rng: np.random.Generator,
) -> tuple[_Selection, NDArray[np.uint8]]:
    """Pass 1 over the features: candidates of each model image (checked) and a random
    sample of them for the k-means, (T, 128), each candidate drawn with ``train_p``."""
    order = np.argsort(np.asarray(model.point3D_ids, dtype=np.uint64), kind="stable")
    by_name = {im.name: im for im in model.images.values()}  # image_by_name is a linear scan
    names, used, sizes, rows, train = [], [], [], [], []
    for name in features:
        image = by_name.get(name)
        if image is None:
            logger.debug("%s: not in the model, its features are not indexed", name)
            continue
        desc, ok, r = _image_selection(model, name, image, features[name], order)
        u = np.flatnonzero(ok)
        names.append(name)
        used.append(u.astype(np.int32))
        sizes.append(len(desc))
        rows.append(r.astype(np.int32))
        if train_p > 0:
            train.append(_rows_of(desc, u[rng.random(len(u)) < train_p]))
    point_rows = np.concatenate(rows) if rows else np.zeros(0, np.int32)
    if len(point_rows) == 0:
        raise InputError("no descriptor of any 3D point of the model: features and model disagree")
    sample = np.concatenate(train) if train else np.zeros((0, DESCRIPTOR_DIM), np.uint8)
    return _Selection(tuple(names), tuple(used), tuple(sizes), point_rows), sample


def _pool_selection(pool: DescriptorPool, options: IndexOptions,
                    rng: np.random.Generator) -> tuple[_Selection, NDArray[np.uint8]]:
    """A materialised pool as a one-image selection, and a k-means sample of it."""
    desc = np.asarray(pool.descriptors)
    if desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_DIM or len(desc) != len(pool.point_rows):
        raise InputError(f"pool descriptors must be (P, 128) with P point rows, got {desc.shape}")
    n = len(desc)
    wanted = 0 if n == 0 or _use_exact(n, options) else \
        _ivf_lists(n, options) * max(1, options.train_per_list)
    pick = np.sort(rng.choice(n, size=min(n, wanted), replace=False))
    sel = _Selection(("pool",), (np.arange(n, dtype=np.int32),), (n,),
                     np.asarray(pool.point_rows, dtype=np.int32))
    return sel, _rows_of(desc, pick)


def _image_descriptors(descriptors_of: Any, sel: _Selection, i: int) -> NDArray[np.uint8]:
    """Image ``i``'s descriptors on a later pass; they must not have changed since pass 1."""
    desc = np.asarray(descriptors_of(sel.names[i]))
    if desc.ndim != 2 or len(desc) != sel.sizes[i]:
        raise InputError(f"{desc.shape[0]} descriptors, {sel.sizes[i]} when first read: "
                         "the features changed while the index was built", path=sel.names[i])
    return desc


def _rank_and_cells(
    sel: _Selection, descriptors_of: Any, max_per_point: int, quantizer: Any | None,
    nlist: int = 0,
) -> tuple[NDArray[np.bool_], NDArray[np.integer[Any]] | None]:
    """Pass 2: (mask of the candidates kept, IVF cell of every candidate or None).

    Only the points with more candidates than ``max_per_point`` are ranked (a small share
    of a large model's points: ranking them all cost ~60 % of the index build time at 1M
    points); the result is the same as ranking every point.
    """
    over = (np.bincount(sel.point_rows) > max_per_point)[sel.point_rows]
    keep = ~over
    if quantizer is None and not over.any():
        return keep, None
    over_idx = np.flatnonzero(over)
    over_desc = np.empty((len(over_idx), DESCRIPTOR_DIM), dtype=np.float32)
    cells = None if quantizer is None else np.empty(len(sel.point_rows), dtype=_cell_type(nlist))
    starts, k = sel.starts, 0
    for i in range(len(sel.names)):
        lo, hi = int(starts[i]), int(starts[i + 1])
        if hi == lo:
            continue
        cand = _rows_of(_image_descriptors(descriptors_of, sel, i), sel.used[i])
        if cells is not None:
            cells[lo:hi] = _assign_cells(quantizer, cand)
        o = over[lo:hi]
        n_over = int(np.count_nonzero(o))
        if n_over:
            over_desc[k:k + n_over] = cand[o]
            k += n_over
    if len(over_idx):
        keep[over_idx[_rank_per_point(over_desc, sel.point_rows[over_idx], max_per_point)]] = True
    return keep, cells


def _cell_type(nlist: int) -> type[np.integer[Any]]:
    """int16 for < 32768 cells: numpy's stable sort of int16 is a radix sort (10× faster)."""
    return np.int16 if nlist <= np.iinfo(np.int16).max else np.int32


def _assign_cells(quantizer: Any, desc: NDArray[np.uint8]) -> NDArray[np.int64]:
    """(N,) nearest cell of each (N, 128) uint8 descriptor, in 16 MB float32 chunks."""
    chunk = 1 << 15
    return np.concatenate([
        quantizer.search(np.ascontiguousarray(desc[s:s + chunk], dtype=np.float32), 1)[1][:, 0]
        for s in range(0, len(desc), chunk)]).astype(np.int64)


def _scatter(sel: _Selection, descriptors_of: Any, keep: NDArray[np.bool_],
             words: NDArray[np.uint64], dest_word: NDArray[np.integer[Any]]) -> None:
    """Pass 3: copy the j-th kept candidate to ``words[dest_word[j]:][:16]``."""
    cols = np.arange(DESCRIPTOR_DIM // 8, dtype=np.int64)
    starts, done = sel.starts, 0  # done: kept candidates of the images before
    for i in range(len(sel.names)):
        lo, hi = int(starts[i]), int(starts[i + 1])
        k = keep[lo:hi]
        n = int(np.count_nonzero(k))
        if n == 0:
            continue
        rows = _rows_of(_image_descriptors(descriptors_of, sel, i), sel.used[i][k])
        dest = dest_word[done:done + n]
        words[dest[:, None].astype(np.int64) + cols] = rows.view(np.uint64).reshape(n, -1)
        done += n


def _word_view(a: NDArray[np.uint8]) -> NDArray[np.uint64]:
    """A C-contiguous, 8-byte aligned uint8 array as uint64 words (same memory)."""
    return a.reshape(-1).view(np.uint64)


def _gather_kept(sel: _Selection, descriptors_of: Any,
                 keep: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """(P, 128) the kept candidates, in candidate order (pass 3 of the exact pool)."""
    pool = np.empty((int(np.count_nonzero(keep)), DESCRIPTOR_DIM), dtype=np.uint8)
    step = DESCRIPTOR_DIM // 8
    _scatter(sel, descriptors_of, keep, _word_view(pool),
             step * np.arange(len(pool), dtype=_word_type(len(pool))))
    return pool


def _training_sample(sel: _Selection, drawn: NDArray[np.uint8], descriptors_of: Any, n: int,
                     rng: np.random.Generator) -> NDArray[np.uint8]:
    """(n, 128) random candidates for the k-means: pass 1's sample, cut down to ``n``.

    When pass 1 drew fewer (features covering far fewer observations than the model holds,
    e.g. re-extracted SIFT), ``n`` candidates are drawn again, one more pass.
    """
    if len(drawn) >= n:
        return drawn[np.sort(rng.choice(len(drawn), size=n, replace=False))]
    pick = np.zeros(len(sel.point_rows), dtype=bool)
    pick[rng.choice(len(pick), size=n, replace=False)] = True
    return _gather_kept(sel, descriptors_of, pick)


def _trained_ivf(train_u8: NDArray[np.uint8], nlist: int, options: IndexOptions) -> Any:
    """An empty FAISS IVF (uint8 codes, ``QT_8bit_direct``) with its k-means cells trained."""
    train = np.ascontiguousarray(train_u8, dtype=np.float32)
    quantizer = _coarse_quantizer(train, options.coarse_dims)
    ivf = faiss.IndexIVFScalarQuantizer(quantizer, DESCRIPTOR_DIM, nlist,
                                        faiss.ScalarQuantizer.QT_8bit_direct, faiss.METRIC_L2,
                                        False)  # store the descriptors, not their residuals
    ivf.cp.seed = int(options.seed)
    ivf.cp.min_points_per_centroid = 1  # small pools: no console warning from FAISS
    ivf.cp.max_points_per_centroid = max(1, options.train_per_list)
    ivf.train(train)  # k-means centroids in 128-d, assigned through the quantizer
    return ivf


def _coarse_quantizer(train: NDArray[np.float32], dims: int) -> Any:
    """The index that assigns descriptors to cells: exact L2 in 128-d, or in the first
    ``dims`` principal components of the training sample (cheaper, consistent for queries
    and pool alike since both go through it)."""
    if dims in (0, DESCRIPTOR_DIM) or len(train) < 4 * DESCRIPTOR_DIM:  # too few for a PCA
        return faiss.IndexFlatL2(DESCRIPTOR_DIM)
    pca = faiss.PCAMatrix(DESCRIPTOR_DIM, dims)
    pca.train(train)
    return faiss.IndexPreTransform(pca, faiss.IndexFlatL2(dims))


@dataclass(frozen=True)
class _IvfLayout:
    """An IVF serialised into one buffer: FAISS's bytes for the trained, empty index with
    its lists section replaced by the lists' sizes, then each list's codes (P_l × 128 bytes)
    and ids (P_l int64), list after list (FAISS's ``ilar``/``full`` format).

    ``faiss.ZeroCopyIOReader`` reads it back with every list a view into this buffer: the
    descriptors are written once, where FAISS searches them, and never copied.
    """

    buffer: NDArray[np.uint8]
    body_at: int  # byte offset of list 0 (8-byte aligned in memory)

    @property
    def words(self) -> NDArray[np.uint64]:
        """The lists as uint64 words: list l's codes start at word 17 × (its first position)."""
        return self.buffer[self.body_at:].view(np.uint64)


def _ivf_layout(ivf: Any, sizes: NDArray[np.int64]) -> _IvfLayout | None:
    """The buffer of ``ivf`` (trained, empty) with lists of these sizes; None when this FAISS
    does not serialise an empty index the way this code expects (then lists are filled)."""
    head = faiss.serialize_index(ivf)
    lists = b"ilar" + struct.pack("<QQ", ivf.nlist, ivf.code_size)
    empty = lists + b"sprs" + struct.pack("<Q", 0)
    if ivf.code_size != DESCRIPTOR_DIM or bytes(head[-len(empty):]) != empty:
        return None
    lists += b"full" + struct.pack("<Q", ivf.nlist) + sizes.astype("<u8").tobytes()
    keep = len(head) - len(empty)
    body_at = keep + len(lists)
    total = body_at + (DESCRIPTOR_DIM + 8) * int(sizes.sum())
    raw = np.empty(total + 8, dtype=np.uint8)
    shift = -(raw.ctypes.data + body_at) % 8
    buf = raw[shift:shift + total]
    buf[:keep] = head[:keep]
    buf[keep:body_at] = np.frombuffer(lists, dtype=np.uint8)
    return _IvfLayout(buf, body_at)


def _read_ivf(layout: _IvfLayout) -> tuple[Any, Any]:
    """(index, the memory its lists live in): zero copy when this FAISS can, else a copy."""
    reader_type = getattr(faiss, "ZeroCopyIOReader", None)
    if reader_type is None:  # older FAISS: the lists are copied, the buffer can go
        return faiss.deserialize_index(layout.buffer), None
    index = faiss.read_index(reader_type(faiss.swig_ptr(layout.buffer), layout.buffer.size))
    return index, (None if _lists_owned(index) else layout.buffer)


def _lists_owned(index: Any) -> bool:
    """True only when the index's first non-empty list is known to own its codes."""
    inv: Any = faiss.downcast_InvertedLists(index.invlists)
    for lst in range(inv.nlist):
        if inv.list_size(lst):
            codes = inv.codes.at(lst)
            return bool(getattr(codes, "is_owned", False))
    return False


def _fill_ivf(sel: _Selection, descriptors_of: Any, keep: NDArray[np.bool_],
              cells: NDArray[np.integer[Any]], ivf: Any) -> tuple[Any, Any, NDArray[np.int32]]:
    """Pass 3 for the IVF: (searchable index, memory its lists live in, point row of each
    pool position). Pool position = place in cell order; FAISS ids are pool positions.

    Peak ~ lists + 40 bytes per descriptor: the arrays over all descriptors are int16 cells,
    the cell order and the destinations (int64), the result's point rows.
    """
    cells_kept = cells[keep]
    order = np.argsort(cells_kept, kind="stable")  # pool position -> kept index
    point_rows = sel.point_rows[keep][order]
    sizes = np.bincount(cells_kept, minlength=ivf.nlist).astype(np.int64)
    first = np.r_[0, np.cumsum(sizes)]  # (nlist + 1,) first pool position of each list
    trim_heap()  # what passes 1-2 freed, before the lists' memory is taken
    layout = _ivf_layout(ivf, sizes)
    # list l's codes start at word 17 × first[l] (the codes and ids of the lists before it),
    # so the code of position p (in list l) is at word first[l] + 16 p; a plain cell-sorted
    # pool (no layout) has it at word 16 p
    dest = _in_chunks(order, lambda o, p: (first[cells_kept[o]] if layout is not None else 0)
                      + (DESCRIPTOR_DIM // 8) * p)
    del order
    trim_heap()
    if layout is None:  # fill FAISS's own lists from a cell-sorted pool (twice the memory)
        logger.debug("FAISS serialises IVFs differently from what this code knows: lists copied")
        pool = np.empty((len(dest), DESCRIPTOR_DIM), dtype=np.uint8)
        _scatter(sel, descriptors_of, keep, _word_view(pool), dest)
        for lst in np.flatnonzero(sizes).tolist():
            a, b = int(first[lst]), int(first[lst + 1])
            ids = np.arange(a, b, dtype=np.int64)
            ivf.invlists.add_entries(lst, b - a, faiss.swig_ptr(ids), faiss.swig_ptr(pool[a:b]))
        ivf.ntotal = len(dest)
        return ivf, None, point_rows
    _scatter(sel, descriptors_of, keep, layout.words, dest)
    del dest
    _write_ids(layout.words, np.sort(cells_kept, kind="stable"), first)
    index, storage = _read_ivf(layout)
    index.ntotal = len(point_rows)
    return index, storage, point_rows


def _word_type(num_descriptors: int) -> type[np.integer[Any]]:
    """int32 word offsets while they fit (17 words per descriptor: < 126M descriptors)."""
    return np.int32 if 17 * num_descriptors < np.iinfo(np.int32).max else np.int64


def _in_chunks(order: NDArray[np.int64],
               fn: Any, chunk: int = 1 << 20) -> NDArray[np.integer[Any]]:
    """``out[order[p]] = fn(order[p], p)`` for every position p, 1M at a time (no
    full-length temporaries)."""
    out = np.empty(len(order), dtype=_word_type(len(order)))
    for a in range(0, len(order), chunk):
        o = order[a:a + chunk]
        out[o] = fn(o, np.arange(a, a + len(o), dtype=np.int64))
    return out


def _write_ids(words: NDArray[np.uint64], sorted_cells: NDArray[np.integer[Any]],
               first: NDArray[np.int64], chunk: int = 1 << 20) -> None:
    """FAISS id of each pool position = the position, after its list's codes: position p of
    list l at word 17 × first[l] + 16 × size_l + (p − first[l]) = 16 × first[l + 1] + p."""
    step = DESCRIPTOR_DIM // 8
    for a in range(0, len(sorted_cells), chunk):
        p = np.arange(a, min(a + chunk, len(sorted_cells)), dtype=np.int64)
        words[step * first[sorted_cells[a:a + chunk].astype(np.int64) + 1] + p] = p.view(np.uint64)


def build_descriptor_index(
    model: SparseModel,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> DescriptorIndex:
    """Index the descriptors of every model observation that has a 3D point.

    ``ImageFeatures`` follow the COLMAP database convention (keypoint i = observation i
    of the image in the model, checked); ``ObservationFeatures`` come from
    ``features_from_images``. Features of images absent from the model are ignored. The
    mapping is read three times, one image at a time: it may read from disk on access.
    """
    return build_index(model, select_index_candidates(model, features, options), features,
                       options)


@dataclass
class IndexCandidates:
    """Pass 1 of the descriptor index (``select_index_candidates``): the descriptors of each
    image that have a 3D point, and a random k-means sample.

    It holds nothing of the model's 2D observations: a caller short of memory drops them
    (``SparseModel.without_observations``, 46 MB at 1M points) before ``build_index``, which
    consumes this (the sample is released during the build).
    """

    selection: _Selection
    sample: NDArray[np.uint8] | None  # (T, 128); None once consumed
    rng: np.random.Generator  # the seeded generator, continued by the build


def select_index_candidates(
    model: SparseModel,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> IndexCandidates:
    """Pass 1 of ``build_descriptor_index``: the only one that reads the observations."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    rng = np.random.default_rng(options.seed)
    p = _train_probability(model, list(features), options)
    sel, sample = _select(model, features, p, rng)
    return IndexCandidates(sel, sample, rng)


def build_index(
    model: SparseModel, candidates: IndexCandidates,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> DescriptorIndex:
    """Passes 2-3 of ``build_descriptor_index`` over the same features; of the model only
    the points are used (its observations may have been dropped)."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    if candidates.sample is None:
        raise ValueError("these index candidates were already built into an index")
    once = [candidates.sample]  # popped by the build, which frees it once trained on
    candidates.sample = None
    return _index(model, lambda _: (candidates.selection, once.pop()), candidates.rng,
                  lambda name: features[name].descriptors, options)


def descriptor_pool(
    model: SparseModel,
    features: Mapping[str, ImageFeatures] | Mapping[str, ObservationFeatures],
    options: IndexOptions | RegistrationOptions,
) -> DescriptorPool:
    """The descriptors of the observations with a 3D point, at most
    ``max_descriptors_per_point`` per point (those nearest the point's mean descriptor)."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    sel, _ = _select(model, features, 0.0, np.random.default_rng(options.seed))
    keep, _ = _rank_and_cells(sel, lambda name: features[name].descriptors,
                              max(1, options.max_descriptors_per_point), None)
    return DescriptorPool(_gather_kept(sel, lambda name: features[name].descriptors, keep),
                          sel.point_rows[keep].astype(np.int64))


def index_pool(model: SparseModel, pool: DescriptorPool,
               options: IndexOptions | RegistrationOptions) -> DescriptorIndex:
    """The searchable index of a descriptor pool: exact search for small pools, else IVF."""
    if isinstance(options, RegistrationOptions):
        options = options.index
    rng = np.random.default_rng(options.seed)
    return _index(model, lambda rng: _pool_selection(pool, options, rng), rng,
                  lambda _: pool.descriptors, options)


def _index(model: SparseModel, select: Any, rng: np.random.Generator, descriptors_of: Any,
           options: IndexOptions) -> DescriptorIndex:
    """The exact pool or the IVF of the candidates: ``select(rng)`` (pass 1) returns them and
    a k-means sample; ``descriptors_of(name)`` gives an image's descriptors (passes 2-3)."""
    sel, drawn = select(rng)
    per_point = max(1, options.max_descriptors_per_point)
    size = int(np.minimum(np.bincount(sel.point_rows), per_point).sum())  # pool size
    searcher = storage = None
    if _use_exact(size, options):
        keep, _ = _rank_and_cells(sel, descriptors_of, per_point, None)
        pool = _gather_kept(sel, descriptors_of, keep)
        point_rows = sel.point_rows[keep]
    else:
        nlist = _ivf_lists(size, options)
        n_train = min(size, nlist * max(1, options.train_per_list))
        train = _training_sample(sel, drawn, descriptors_of, n_train, rng)
        del drawn
        ivf = _trained_ivf(train, nlist, options)
        del train
        keep, cells = _rank_and_cells(sel, descriptors_of, per_point, ivf.quantizer, nlist)
        assert cells is not None  # a quantizer was given
        searcher, storage, point_rows = _fill_ivf(sel, descriptors_of, keep, cells, ivf)
        searcher.nprobe = min(nlist, options.ivf_probe)
        pool = np.zeros((0, DESCRIPTOR_DIM), np.uint8)
    trim_heap()  # the passes' temporaries go back to the OS
    method = "exact" if searcher is None else "ivf"
    logger.info("descriptor index: %d descriptors of %d points (%s%s)", len(point_rows),
                np.count_nonzero(np.bincount(point_rows)), method,
                "" if searcher is None else f", {searcher.nlist} cells, probe {searcher.nprobe}")
    return DescriptorIndex(
        descriptors=pool, point_rows=point_rows,
        points_xyz=np.asarray(model.points_xyz, dtype=np.float64),
        point3D_ids=np.asarray(model.point3D_ids, dtype=np.uint64),
        method=method,
        ivf_lists=0 if searcher is None else int(searcher.nlist),
        ivf_probe=0 if searcher is None else int(searcher.nprobe),
        _searcher=searcher, _storage=storage,
    )


def _use_exact(num_descriptors: int, options: IndexOptions) -> bool:
    """Exact brute force or the IVF for a pool of this size."""
    if options.exact is not None:
        return bool(options.exact)
    return num_descriptors <= options.exact_max_pool


def _exact_knn(pool: NDArray[np.float32], query: NDArray[np.float32], k: int) -> tuple[
        NDArray[np.int64], NDArray[np.float32]]:
    """(Q, min(k, P)) exact nearest neighbours and their L2 distances, sorted by distance.

    FAISS's flat L2 index: BLAS distances and a heap per query. numpy's row-wise
    ``argpartition`` over the (Q, P) distance matrix took 0.67 s for one 640 x 480 image
    (6915 queries, 5604 descriptors) against 0.05 s here."""
    k = min(k, len(pool))
    if k == 0:
        return np.zeros((len(query), 0), np.int64), np.zeros((len(query), 0), np.float32)
    flat = faiss.IndexFlatL2(pool.shape[1])
    flat.add(np.ascontiguousarray(pool, dtype=np.float32))
    d2, idx = flat.search(np.ascontiguousarray(query, dtype=np.float32), k)
    return np.asarray(idx, dtype=np.int64), np.sqrt(np.maximum(d2, 0.0)).astype(np.float32)


def _knn(index: DescriptorIndex, query: NDArray[np.float32], k: int) -> tuple[
        NDArray[np.int64], NDArray[np.float32]]:
    """(Q, k) pool indices and L2 distances of the k nearest descriptors (sorted)."""
    if index.method == "exact":
        return _exact_knn(index.descriptors.astype(np.float32), query, k)
    d2, idx = index._searcher.search(query, k)  # FAISS: squared L2, −1 for no neighbour found
    idx = np.asarray(idx, dtype=np.int64)
    dist = np.where(idx >= 0, np.sqrt(np.maximum(d2, 0)), np.inf).astype(np.float32)
    return np.maximum(idx, 0), dist
