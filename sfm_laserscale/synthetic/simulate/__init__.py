"""The paper's synthetic experiments (Istenič et al. 2020), run through the code of ``scale``.

In data-flow order: :mod:`.configs` (the laser configurations A, B, C, the camera and the
options), :mod:`.areas` (the metric scene and its smooth and rough areas), :mod:`.views` (the
true views of each mode), :mod:`.trial` (one view: noisy features -> ``estimate_pose`` ->
noisy spots -> ``cast_spots`` -> ``estimate_image`` -> per-view fusion), :mod:`.samples` (the
trials as rows of estimates; PCM-joint groups), :mod:`.runner` (trials in worker processes,
``simulate``), :mod:`.stats` (error statistics per setting and method), :mod:`.tables`
(table.md). The ``simulate`` command (:mod:`sfm_laserscale.commands.simulate`) writes the
outputs; docs/SIMULATE.md describes the experiments and their results.
"""
