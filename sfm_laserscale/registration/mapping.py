"""COLMAP incremental mapping options (pycolmap), built once for every SfM this package runs: the
demo's data set (:mod:`sfm_laserscale.synthetic.dataset`) and the pycolmap backend of the COLMAP
plugin (plugins/colmap)."""

from __future__ import annotations

import pycolmap


def mapping_options(seed: int, fixed_intrinsics: bool,
                    min_model_size: int | None = None) -> pycolmap.IncrementalPipelineOptions:
    """Incremental mapping seeded wherever pycolmap takes a seed (the pipeline, the mapper and the
    triangulation). ``fixed_intrinsics``: the known camera is held fixed by bundle adjustment and
    absolute-pose refinement; ``min_model_size``: the smallest model kept (None: COLMAP's)."""
    opts = pycolmap.IncrementalPipelineOptions()
    if min_model_size is not None:
        opts.min_model_size = int(min_model_size)
    if fixed_intrinsics:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.mapper.abs_pose_refine_focal_length = False
        opts.mapper.abs_pose_refine_extra_params = False
    opts.random_seed = int(seed)
    opts.mapper.random_seed = int(seed)
    opts.triangulation.random_seed = int(seed)
    return opts
