"""The stages that append ``scale`` to whole pipelines (the ``colmap`` and ``openmvg`` commands):
running their external tools step by step (:mod:`.tools`), keeping the laser images out of SfM
(:mod:`.hold_out`), COLMAP's command-line SfM (:mod:`.colmap_sfm`) and the OpenMVG + OpenMVS
command sequence (:mod:`.openmvg_steps`). Re-exports nothing.
"""
