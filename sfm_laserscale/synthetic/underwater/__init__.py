"""Independent, physically described generator of underwater laser-scaler photographs.

Shares no code and no parameter with the detector (``sfm_laserscale.detection``) nor with the
older synthetic renderer (``synthetic.spots``/``render``/``scene``): it imports only numpy,
scipy and OpenCV. Modules: :mod:`.optics` (camera model), :mod:`.spectra` (sensor and light
spectra), :mod:`.water` (water types), :mod:`.surface` and :mod:`.texture` (the seafloor),
:mod:`.seafloor` (lit scene, clutter, marine snow, hot spots), :mod:`.beams` (laser spots),
:mod:`.sensor` (Bayer sensor, camera processing, JPEG), :mod:`.conditions` (named
benchmark conditions and :func:`~.conditions.render_frame`) and :mod:`.views` (one seafloor
fixed in a world frame, photographed from explicit poses).

:mod:`.survey` (a multi-view survey data set for end-to-end runs of ``scale``) is the one
module that imports from the rest of the package: pycolmap SfM and the writers of
``synthetic.dataset``, never the stages under test.
"""

from sfm_laserscale.synthetic.underwater.conditions import CONDITIONS, Frame, render_frame

__all__ = ["CONDITIONS", "Frame", "render_frame"]
