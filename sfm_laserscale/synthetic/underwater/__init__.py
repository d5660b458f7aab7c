"""Independent, physically described generator of underwater laser-scaler photographs.

Shares no code and no parameter with the detector (``sfm_laserscale.detection``) nor with the
older synthetic renderer (``synthetic.spots``/``render``/``scene``): it imports only numpy,
scipy and OpenCV. Modules: :mod:`.optics` (camera model), :mod:`.spectra` (sensor and light
spectra), :mod:`.water` (water types), :mod:`.surface` and :mod:`.texture` (the seafloor),
:mod:`.seafloor` (lit scene, clutter, marine snow, hot spots), :mod:`.beams` (laser spots),
:mod:`.sensor` (Bayer sensor, camera processing, JPEG) and :mod:`.conditions` (named
benchmark conditions and :func:`~.conditions.render_frame`).
"""

from sfm_laserscale.synthetic.underwater.conditions import CONDITIONS, Frame, render_frame

__all__ = ["CONDITIONS", "Frame", "render_frame"]
