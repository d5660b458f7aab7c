"""Settings and results of spot detection (lengths in pixels unless named otherwise)."""

from __future__ import annotations

from dataclasses import dataclass, field

from sfm_laserscale.errors import InputError
from sfm_laserscale.model import Spot

#: which rule took a spot (``Candidate.taken_by``): its own evidence (the joint choice, a whitened
#: core's rules, a pair), the floor search (through the other spots, or a lone spot's floor)
#: or the second look (below the clutter gate, or its clutter term waived)
TAKEN_ON_OWN = "own evidence"
TAKEN_ON_FLOOR = "floor search"
TAKEN_ON_SECOND_LOOK = "second look"
#: what a spot taken by the floor search, or by the second look, adds to its σ per axis, as a
#: share of the floor search's radius: set so that 95 % of those spots' per-axis errors lie
#: within 1.96 σ on the physical benchmark (docs/DETECTION.md, "The rule that took a spot")
FLOOR_CHOICE = 0.2
SECOND_LOOK_CHOICE = 0.5


@dataclass(frozen=True)
class SigmaModel:
    """A spot's localisation σ beyond its noise (docs/DETECTION.md, "The localisation σ").

    σ² = σ_noise² + (window_gain · shift)² + (asymmetry_gain · √A · σ_w)² + floor_px², with
    ``shift`` (px) how far the centroid's fixed point moves when its window widens
    (:data:`~sfm_laserscale.detection.refine.WIDE_WINDOW_RATIO`), A the spot's
    :func:`~sfm_laserscale.detection.refine.asymmetry` and σ_w its window (px). A spot
    centred on two signals (:mod:`~sfm_laserscale.detection.centre`) adds
    (disagreement_gain · d)², d (px) the distance between their centres: 1/√8 is the σ per
    axis of the mean of two estimates with independent errors of equal σ, given d. A centre
    read from colour (the texture-free light: a colour difference, which the Bayer mosaic
    samples at every second pixel and 4:2:0 chroma in 2 × 2 blocks) adds
    (chroma_px / max(1, r))², r (px) the spot's half-maximum radius: a block's pull on a
    centroid shrinks as the spot grows. A spot cut by the image border (fitted by a 2D Gaussian,
    with no wide-window term) adds (window_gain · d)², d (px) the distance from the fit to the
    centroid whose window keeps only pixels mirrored inside the image
    (:func:`~sfm_laserscale.detection.refine.cut_sigma`). A spot taken by the floor search
    or the second look adds (share · R)², R the floor search's radius (px) and share
    ``floor_choice`` or ``second_look_choice``: those rules take a maximum beside the spot more
    often than the first pass does, which the blob's own terms do not see.
    """

    floor_px: float = 0.1
    window_gain: float = 0.5
    asymmetry_gain: float = 0.12
    disagreement_gain: float = 0.354
    chroma_px: float = 0.3
    floor_choice: float = 0.0
    second_look_choice: float = 0.0

    def chroma(self, radius_px: float) -> float:
        """The colour term (px, per axis) of a centre read from colour, for a spot of
        half-maximum radius ``radius_px``."""
        return self.chroma_px / max(1.0, radius_px)

    def choice(self, taken_by: str, floor_radius_px: float) -> float:
        """The term (px, per axis) of the rule ``taken_by`` that took a spot (0 for a spot
        taken on its own evidence), in an image whose floor search radius is
        ``floor_radius_px``."""
        share = {TAKEN_ON_FLOOR: self.floor_choice,
                 TAKEN_ON_SECOND_LOOK: self.second_look_choice}.get(taken_by, 0.0)
        return share * floor_radius_px


@dataclass(frozen=True)
class DetectionOptions:
    """Settings of :func:`sfm_laserscale.detection.detect_spots`.

    Where to look:

    - ``min_range_m``/``max_range_m``: part of each beam (metres from its origin along the beam)
      where spots are searched; its projection is the beam's image segment.
    - ``band_px``: max distance of a spot centre from its beam segment; None = 3 px + 0.5 % of
      the image diagonal (≈ 14 px at 1920×1080), to absorb calibration error.

    What a candidate is:

    - ``spot_sigmas_px``: blob scales (Gaussian sigma) searched by the DoG.
    - ``ridge_free_brightness``: the brightness response's blobs (a green laser's spots, a
      clipped core) are found, valued and judged against the scene on its ridge-free blob
      response (the Hessian's flattest curvature, :func:`.response.ridge_free_response`):
      brightness holds every edge of the scene's texture and the beams' glows in the water,
      along which the DoG peaks and a spot beside or on one is no maximum of its own. False:
      on its DoG, as the colour response is.
    - ``max_spot_radius_px``: larger half-maximum radius = not a spot; None = 1.5 % of the
      diagonal (≈ 33 px at 1920×1080).
    - ``min_snr``: peak contrast over the local background noise, below which a blob is no
      candidate.
    - ``max_annulus_ratio``: compactness; the 75th percentile of the response in a ring around
      the spot, relative to its peak contrast, must stay below this.
    - ``min_clutter_ratio``: maxima whose blob response is below this many times the scene's
      *clutter level* (the 99th percentile of the response at all its local maxima in the
      searched region, :func:`clutter_level`) are listed, not measured. 0 measures them all.
    - ``second_look_clutter_ratio``: maxima inside a beam's band between this and
      ``min_clutter_ratio`` clutter levels are measured too (at most 12 per response), for a
      second look: a laser left without a spot takes one of them where its light has the
      laser's colour and its range agrees with the other lasers' spots (:mod:`.assign`).
      ``min_clutter_ratio`` or more switches the second look off.
    - ``saturation_level``: channel value (0–1) above which a pixel counts as clipped.
    - ``max_candidates``: strongest local maxima measured per colour and response.
    - ``input_gamma``: pixel values are decoded as ``(v / 255) ** input_gamma`` before anything
      else (2.2 for gamma-encoded camera JPEGs, 1.0 for linear images).
    - ``response``: "background" (default: the laser channel relative to the local background
      colour, and the plain colour difference; see :mod:`.response`) or "difference" (the plain
      colour difference only).

    How a candidate scores (the evidence multiplies, see :mod:`.score`):

    - ``snr_half``: SNR at which the contrast term is 0.5.
    - ``clutter_half``: blob response, in clutter levels, at which the clutter term is 0.5.
    - ``colour_tau``: width of the colour evidence: the term is the logistic of
      (laser-coloured share of the light a candidate adds − ½) / tau.
    - ``colour_evidence``: False leaves colour out of the score (a neutral calibration target,
      whose black/white edges through a spot look like light of the target's colour).
    - ``min_score``: an assigned spot with a lower score is reported in ``missing`` instead.
    - ``alone_min_score``: the score a spot needs when it is alone in its image (no other
      laser's spot after the floor search and the second look, while two or more other
      calibrated beams are in view): nothing corroborates it, and the bands of laser-free
      photographs hold blobs that score 0.25-0.6 on their own (docs/DETECTION.md).

    Where the other spots put a missing one (:mod:`.floor`):

    - ``floor_search``: a calibrated laser left without a spot is searched where the floor
      through the other lasers' spots (a plane) meets its beam.
    - ``floor_min_spots``: spots of other calibrated lasers needed for that plane (>= 2).
    - ``floor_radius_px``: largest distance of such a spot from that point; None = 0.14 % of
      the image diagonal (3.1 px at 1920×1080, 7 px at 4000×3000): the floor's relief and the
      rig's calibration error move a spot in proportion to the focal length.
    - ``floor_weak_min_snr``: where that search takes no candidate, it searches again with the
      weak-spot test at this SNR instead of ``min_snr`` (None, or a value not below
      ``min_snr``: not); the evidence still has to reach ``min_score``, so a low SNR is taken
      only with the laser's colour and a round shape (:func:`.floor.floor_search`).

    Sub-pixel centre:

    - ``refine``: "centroid" (Gaussian-windowed centroid iterated to its fixed point, the
      default) or "gaussian" (2D Gaussian fit to the unclipped pixels). Spots cut by the image
      border always use the fit.
    - ``two_signal_centre``: a luma-dominant (green) laser's chosen spot, and any laser's
      clipped core, is refined on both of its signals, the texture-free light and luma: a
      green clipped core takes their mean when they agree, a clipped core whose two centres
      disagree takes the one of a 3× smaller σ (a red or blue core only luma's), and the σ
      gains their disagreement (a red or blue core's only where it takes luma's;
      :mod:`.centre`).
    - ``fit_agree_sigmas``: an unclipped chosen spot takes the centre of a 2D Gaussian fit
      where the centroid's window was too wide for it (``centre.WIDE_WINDOW`` × the fitted σ
      or more) and the fit lies within this many of its σ from the centroid
      (:func:`.centre.fit_centre`; its σ is kept); 0 switches it off.
    - ``narrow_window_ratio``: a chosen spot (not one refined beside an overlapping one) is
      refined again under centroid windows narrower than its measured radius (2, 1.5 and 1 px),
      and takes the centre whose stated σ is this many times smaller than its own
      (:func:`.centre.narrow_window_centre`); 0 switches it off.
    - ``crosstalk_max_noise_px``: a red or blue laser's chosen clipped core is centred again
      on the channels other than its laser's (the sensor's crosstalk), and takes that centre
      where its noise σ is at most this (px), it lies within max(3 px, 1.5 half-maximum
      radii) of the centre it had and its stated σ is smaller than that centre's
      (:func:`.centre.crosstalk_centre`); 0 switches it off.
    - ``lone_floor_spots``: with one laser's spot found, the other beams are searched where a
      floor through it puts them (:mod:`.lone`), and the spots found there are taken when this
      many beams or more hold one (then the floor search through all of them); 0 switches it
      off. ``lone_floor_reach_px``: the part of each beam's segment searched, each side of
      where a floor facing the camera puts the spot (None: 5 floor-search radii).
    - ``wide_maximum_ratio``: near a predicted point (the floor search), a maximum whose
      half-maximum radius is this many times the image's other spots' median radius or more,
      and whose own centroid window centres it beyond max(2 px, that radius) from itself, is
      refined at that radius, and takes that centre where it holds
      (:func:`.candidates._refined`); so is a chosen spot that wide, against the other chosen
      spots (:func:`.wandered.narrow_wide_spots`); 0 switches both off.
    - ``peak_apart_px``: a chosen spot measured from a maximum of the brightness response
      whose centre lies beyond max(this, half its half-maximum radius) of that maximum takes
      the maximum's sub-pixel peak (:func:`.wandered.back_to_peak`); 0 switches it off.
    - ``peak_when_refinement_fails``: a round maximum of the brightness response whose
      sub-pixel refinement fails (its centroid runs off it) is centred at its sub-pixel peak,
      with a wider σ, rather than rejected (:func:`.candidates._at_peak`).
    - ``luma_separation_radii``: a luma-dominant (green) laser's spots are refined with a
      neighbour's light removed (read on the texture-free light alone) only when their centres
      lie within this many half-maximum radii (theirs summed); None: when their refinement
      windows overlap, as red and blue spots (:func:`.candidates.overlap_reach`).
    - ``sigma_floor_px``, ``sigma_window_gain``, ``sigma_asymmetry_gain``,
      ``sigma_disagreement_gain``, ``sigma_chroma_px``: the localisation sigma's terms beyond
      noise (:class:`SigmaModel`): a floor (demosaicing, JPEG chroma), light that is not
      point-symmetric about the centre, the distance between two signals' centres, and the
      2 × 2 sampling of colour for a centre read from it.
    - ``sigma_floor_choice``, ``sigma_second_look_choice``: what a spot taken by the floor
      search or by the second look adds to its σ, as a share of the floor search's radius
      (:meth:`SigmaModel.choice`).
    - ``scene_texture_sigma_px``: with a scene reference (``detect_spots(..., scene_rgb=)``),
      its texture finer than this Gaussian sigma is subtracted from the image before
      detection (:mod:`.scene`). ``scene_gain_sigma_px``: that texture is first scaled to
      the image's own, per channel, by a least-squares gain over a Gaussian window of this
      sigma (the image lit otherwise than the reference: lamp hot spots); None: unscaled.
    """

    min_range_m: float = 0.5
    max_range_m: float = 10.0
    band_px: float | None = None
    spot_sigmas_px: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
    ridge_free_brightness: bool = True
    max_spot_radius_px: float | None = None
    min_snr: float = 5.0
    max_annulus_ratio: float = 0.5
    min_clutter_ratio: float = 1.5
    second_look_clutter_ratio: float = 0.7
    saturation_level: float = 250.0 / 255.0
    max_candidates: int = 100
    input_gamma: float = 2.2
    response: str = "background"
    snr_half: float = 6.0
    clutter_half: float = 1.5
    colour_tau: float = 0.07
    colour_evidence: bool = True
    min_score: float = 0.25
    alone_min_score: float = 0.6
    floor_search: bool = True
    floor_min_spots: int = 2
    floor_radius_px: float | None = None
    floor_weak_min_snr: float | None = 2.5
    refine: str = "centroid"
    sigma_floor_px: float = 0.1
    sigma_window_gain: float = 0.5
    sigma_asymmetry_gain: float = 0.12
    two_signal_centre: bool = True
    fit_agree_sigmas: float = 3.0
    narrow_window_ratio: float = 2.0
    wide_maximum_ratio: float = 2.0
    peak_apart_px: float = 1.2
    peak_when_refinement_fails: bool = True
    crosstalk_max_noise_px: float = 0.05
    lone_floor_spots: int = 2
    lone_floor_reach_px: float | None = None
    luma_separation_radii: float | None = 3.0
    sigma_disagreement_gain: float = 0.354
    sigma_chroma_px: float = 0.3
    sigma_floor_choice: float = FLOOR_CHOICE
    sigma_second_look_choice: float = SECOND_LOOK_CHOICE
    scene_texture_sigma_px: float = 8.0
    scene_gain_sigma_px: float | None = 24.0

    @property
    def sigma_model(self) -> SigmaModel:
        """The localisation sigma's terms beyond noise."""
        return SigmaModel(self.sigma_floor_px, self.sigma_window_gain, self.sigma_asymmetry_gain,
                          self.sigma_disagreement_gain, self.sigma_chroma_px,
                          self.sigma_floor_choice, self.sigma_second_look_choice)

    def __post_init__(self) -> None:
        if not 0.0 < self.min_range_m < self.max_range_m:
            raise InputError(f"detection range must satisfy 0 < min < max, got "
                             f"{self.min_range_m:g}..{self.max_range_m:g} m")
        if not self.input_gamma > 0:
            raise InputError(f"input_gamma must be positive, got {self.input_gamma}")
        if self.response not in ("background", "difference"):
            raise InputError(f"response must be 'background' or 'difference', got "
                             f"{self.response!r}")
        if self.refine not in ("centroid", "gaussian"):
            raise InputError(f"refine must be 'centroid' or 'gaussian', got {self.refine!r}")
        for name in ("min_clutter_ratio", "second_look_clutter_ratio", "alone_min_score",
                     "sigma_floor_px", "sigma_window_gain", "sigma_asymmetry_gain",
                     "sigma_disagreement_gain", "sigma_chroma_px", "sigma_floor_choice",
                     "sigma_second_look_choice", "fit_agree_sigmas",
                     "narrow_window_ratio", "wide_maximum_ratio", "crosstalk_max_noise_px",
                     "peak_apart_px"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("snr_half", "clutter_half", "colour_tau", "scene_texture_sigma_px"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be positive, got {getattr(self, name)}")
        if not self.spot_sigmas_px or min(self.spot_sigmas_px) <= 0:
            raise InputError("spot_sigmas_px must be positive")
        for name in ("narrow_window_ratio", "wide_maximum_ratio"):
            if 0 < getattr(self, name) < 1:
                raise InputError(f"{name} must be 0 (off) or at least 1, got "
                                 f"{getattr(self, name)}")
        if self.lone_floor_spots < 0:
            raise InputError(f"lone_floor_spots must be >= 0, got {self.lone_floor_spots}")
        if self.floor_min_spots < 2:
            raise InputError(f"floor_min_spots must be >= 2, got {self.floor_min_spots}")
        for name in ("band_px", "max_spot_radius_px", "floor_radius_px", "lone_floor_reach_px",
                     "luma_separation_radii", "floor_weak_min_snr", "scene_gain_sigma_px"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise InputError(f"{name} must be positive, got {value}")


@dataclass(frozen=True)
class Candidate:
    """One local maximum of a response, as measured, and what became of it.

    ``x``/``y``: refined centre (COLMAP convention). ``color``: the channel searched.
    ``source``: the response it came from, "colour" (the laser's colour over the background) or
    "bright" (a compact bright blob, whatever its hue, in a green laser's band or where the
    laser channel clips).
    ``response``: its blob (DoG) value; ``clutter_ratio``: that value in clutter levels of the
    scene (:func:`~sfm_laserscale.detection.response.clutter_level`). ``score``: the product
    of the evidence terms in ``evidence`` (name -> value in 0–1: contrast, roundness, clutter,
    colour, beam) of the nearest admissible laser (0 when a test rejected it). ``laser``: the
    laser it was assigned to, or None. ``reason``: "assigned to L1", or the test it failed.
    ``taken_by``: for a spot, the rule that took it (TAKEN_ON_OWN, TAKEN_ON_FLOOR,
    TAKEN_ON_SECOND_LOOK); "" for the others.
    """

    x: float
    y: float
    color: str
    response: float
    snr: float
    radius_px: float
    roundness: float
    score: float
    laser: str | None
    reason: str
    source: str = "colour"
    evidence: tuple[tuple[str, float], ...] = ()
    clutter_ratio: float = float("inf")
    taken_by: str = ""


@dataclass(frozen=True)
class DetectionResult:
    """Assigned spots, every candidate considered, lasers without a spot (name -> reason) and,
    for each of those, the best candidates in its band (``near_misses``, named in the reason)."""

    spots: tuple[Spot, ...]
    candidates: tuple[Candidate, ...]
    missing: dict[str, str] = field(default_factory=dict)
    near_misses: dict[str, tuple[Candidate, ...]] = field(default_factory=dict)

    def taken_by(self) -> dict[str, str]:
        """Laser -> the rule that took its spot (TAKEN_ON_OWN, TAKEN_ON_FLOOR,
        TAKEN_ON_SECOND_LOOK)."""
        return {c.laser: c.taken_by for c in self.candidates if c.laser and c.taken_by}
