"""Registration of held-out (laser) images into an existing sparse model.

The steps, in data-flow order: :mod:`.sift` (COLMAP's SIFT on an image), :mod:`.ties` (SIFT
re-extracted on the model's images, tied to its observations), :mod:`.features` (the model's
descriptors from whatever holds them: a COLMAP database, OpenMVG regions or re-extraction),
:mod:`.index` (descriptor index of the model's 3D points), :mod:`.match` (2D–3D matches),
:mod:`.pose` (absolute pose, acceptance rule, pose covariance; ``register_image`` chains match
and pose). :mod:`.sift_workers` extracts SIFT in worker processes; :mod:`.mapping` builds the
COLMAP incremental-mapping options of the demo and the COLMAP plugin; :mod:`.options` holds
every step's settings.

This package is the one place that calls pycolmap's SIFT extractor and estimators: pycolmap API
drift stays here. The pose covariance, the refinement loss, the index's design and the
determinism guarantees are described in docs/REGISTRATION.md.
"""
