"""Tactile optical flow: contact strength and location from dome camera frames.

Per frame (grey, full resolution, e.g. 640 x 480)::

    frame --resize by work_scale--> work image --gain/offset matched to the reference-->
    DIS optical flow reference -> frame (work px) --block mean over grid_px full px-->
    coarse flow (Hg, Wg, 2) in full-resolution px --natural HHD (hhd.py)-->
    div of the curl-free part (areal strain, dimensionless) --Gaussian smoothing-->
    strength = its peak inside the dome mask; location = divergence-weighted centroid of
    the connected region around that peak where it exceeds region_fraction * peak.

Why positive divergence: an indenter pushes the membrane towards the camera and
stretches it, so the dots around the contact spread outwards (a source of flow, div > 0),
surrounded by a ring of weak compression (div < 0, spread over a much larger area).
The source region is compact and centred on the contact, so its centroid is the contact
location; the curl-free part is used because shear (a translation of the gel: harmonic)
and twist (curl) carry no information about where the indenter presses.

Contact decisions need the noise level of ``strength``, which is measured on frames known
to be free of contact (the first ones after the reference), so they are made afterwards
over the whole sequence by :func:`decide_contacts` (hysteresis on two thresholds).

Units: pixel coordinates (u, v) are full-resolution image coordinates with pixel centres
at integers; flow is in full-resolution px; strength is dimensionless (px/px).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from tacest.errors import TacestError
from tacest.sensors.dome import DomeCalibration
from tacest.sensors.hhd import divergence, hhd

#: DIS settings: (finest pyramid level, patch size, patch stride, gradient-descent
#: iterations, variational-refinement iterations).  "tactile" is ours: OpenCV's "medium"
#: with a coarser stride and fewer iterations.  Measured on 640x480 synthetic sequences
#: at work_scale 0.5 (benchmarks/bench_video.py --compare): "fast" and "ultrafast" stop
#: at pyramid level 2 (80 x 60 px), where the dots are sub-pixel, and lose weak contacts
#: (F1 0.97-0.98, median normal error 2.4-3.4 deg); "medium" matches "tactile" in
#: accuracy at twice the cost.
#: The HHD domain: the dome disc up to this fraction of the rim radius.  Outside the rim
#: there are no dots and the flow is noise; the rim's soft edge (and a grid cell
#: straddling it) is left out with a 3 % margin.
HHD_DOMAIN_RHO = 0.97

DIS_PRESETS = {
    "tactile": (1, 8, 4, 16, 5),
    "ultrafast": (2, 8, 4, 12, 0),
    "fast": (2, 8, 4, 16, 5),
    "medium": (1, 8, 3, 25, 5),
}
FLOW_METHODS = ("dis", "farneback")


@dataclass
class FlowSettings:
    """How flow and the divergence map are computed (all documented in docs/tactile_video.md).

    method : "dis" (default; ~1-4 ms at 320 x 240) or "farneback" (~12 ms, for comparison)
    dis_preset : "tactile" (default) | "ultrafast" | "fast" | "medium" (see DIS_PRESETS)
    work_scale : frames are resized by this factor before the flow (0.5: 640x480 -> 320x240)
    grid_px : full-resolution px per HHD grid cell (8: an 80 x 60 grid on 640 x 480; the
        flow is block-averaged over round(grid_px * work_scale) work px)
    smooth_cells : sigma, in grid cells, of the Gaussian smoothing of the divergence map
    mask_rho : contacts are looked for within this fraction of the rim radius (the rim's
        own edge makes flow artefacts)
    region_fraction : the contact region is where the smoothed divergence exceeds this
        fraction of its peak (connected to the peak)
    match_brightness : rescale each work image to the reference's mean and standard
        deviation inside the dome before the flow (undoes global lighting drift)
    """

    method: str = "dis"
    dis_preset: str = "tactile"
    work_scale: float = 0.5
    grid_px: int = 8
    smooth_cells: float = 1.0
    mask_rho: float = 0.9
    region_fraction: float = 0.5
    match_brightness: bool = True

    def check(self):
        if self.method not in FLOW_METHODS:
            raise TacestError(f"flow method must be one of {', '.join(FLOW_METHODS)}, got {self.method!r}")
        if self.dis_preset not in DIS_PRESETS:
            raise TacestError(f"DIS preset must be one of {', '.join(DIS_PRESETS)}, got {self.dis_preset!r}")
        if not 0.05 <= self.work_scale <= 1.0:
            raise TacestError(f"flow scale must be in [0.05, 1], got {self.work_scale}")
        if not (isinstance(self.grid_px, int) and self.grid_px >= 1):
            raise TacestError(f"grid size must be a positive integer number of px, got {self.grid_px!r}")
        if not 0.1 <= self.mask_rho <= 1.0:
            raise TacestError(f"mask radius must be in [0.1, 1] of the rim radius, got {self.mask_rho}")
        if not 0.0 < self.region_fraction < 1.0:
            raise TacestError(f"region fraction must be in (0, 1), got {self.region_fraction}")
        return self


@dataclass
class DetectSettings:
    """Contact decision on the per-frame strength (peak divergence, dimensionless).

    noise_frames : the frames after the reference used to measure the no-contact level
        (they must be free of contact)
    k_on, k_off : contact starts when strength > k_on * noise and ends when it drops below
        k_off * noise (hysteresis: k_off < k_on avoids chatter at the threshold)
    min_strain : floor of the on-threshold (areal strain), so clean images with a near-zero
        noise level do not turn every flicker into a contact; the off-floor is scaled by
        k_off / k_on
    """

    noise_frames: int = 10
    k_on: float = 3.0
    k_off: float = 2.0
    min_strain: float = 0.02

    def check(self):
        if self.noise_frames < 1:
            raise TacestError(f"noise frames must be >= 1, got {self.noise_frames}")
        if not (self.k_on > 0 and 0 < self.k_off <= self.k_on):
            raise TacestError(f"thresholds need 0 < k_off <= k_on, got k_on={self.k_on}, k_off={self.k_off}")
        if not self.min_strain >= 0:
            raise TacestError(f"min strain must be >= 0, got {self.min_strain}")
        return self


@dataclass
class FrameAnalysis:
    """What one frame shows.

    strength : float, peak smoothed divergence of the curl-free flow inside the mask (px/px)
    uv : (2,) float, full-res px, centroid of the contact region (NaN if no positive peak)
    shear : (2,) float, px, mean harmonic flow inside the mask (gel translation)
    twist : float, mean curl inside the contact region (rad-like, px/px)
    """

    strength: float
    uv: np.ndarray
    shear: np.ndarray
    twist: float
    debug: dict = field(default_factory=dict, repr=False)


class TactileFlow:
    """Flow-based contact analysis of frames against one reference frame.

    Parameters
    ----------
    calib : DomeCalibration (its image_size must be the frames' size)
    settings : FlowSettings
    """

    def __init__(self, calib: DomeCalibration, settings: FlowSettings | None = None):
        import cv2

        self._cv2 = cv2
        self.calib = calib
        self.settings = (settings or FlowSettings()).check()
        s = self.settings
        W, H = calib.image_size
        self.work_size = (max(8, int(round(W * s.work_scale))), max(8, int(round(H * s.work_scale))))
        # the effective scale per axis after rounding
        self.scale_xy = np.array([self.work_size[0] / W, self.work_size[1] / H])
        Ww, Hw = self.work_size
        self.grid_step = max(1, int(round(s.grid_px * s.work_scale)))  # work px per grid cell
        self.grid_shape = (Hw // self.grid_step, Ww // self.grid_step)
        if min(self.grid_shape) < 8:
            raise TacestError(f"the analysis grid {self.grid_shape[1]}x{self.grid_shape[0]} is too coarse; "
                              "use a larger flow scale or a smaller grid size")
        Hg, Wg = self.grid_shape
        # grid cell centres in full-resolution px (pixel centres at integers):
        # work = (grid + 0.5) * step - 0.5 ; full = (work + 0.5) / scale - 0.5
        gx = ((np.arange(Wg) + 0.5) * self.grid_step) / self.scale_xy[0] - 0.5
        gy = ((np.arange(Hg) + 0.5) * self.grid_step) / self.scale_xy[1] - 0.5
        self.grid_u, self.grid_v = np.meshgrid(gx, gy)
        # spacing of the grid in full px (mean of the axes; they differ only by rounding)
        self.spacing = float(self.grid_step / self.scale_xy.mean())
        rho = np.hypot(self.grid_u - calib.center_px[0], self.grid_v - calib.center_px[1]) / calib.rim_radius_px
        self.mask = rho < s.mask_rho
        #: the HHD's domain: the dome's disc short of its rim, where the dots are
        self.domain = rho < HHD_DOMAIN_RHO
        if self.mask.sum() < 9:
            raise TacestError("the dome mask covers fewer than 9 grid cells; check center_px and rim_radius_px")
        # work-resolution mask of the dome (for brightness matching)
        wu = (np.arange(Ww) + 0.5) / self.scale_xy[0] - 0.5
        wv = (np.arange(Hw) + 0.5) / self.scale_xy[1] - 0.5
        wr = np.hypot(wu[None, :] - calib.center_px[0], wv[:, None] - calib.center_px[1]) / calib.rim_radius_px
        self._work_mask = (wr < 1.0).astype(np.uint8)
        if s.method == "dis":
            finest, patch, stride, gd_iters, var_iters = DIS_PRESETS[s.dis_preset]
            dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
            dis.setFinestScale(finest)
            dis.setPatchSize(patch)
            dis.setPatchStride(stride)
            dis.setGradientDescentIterations(gd_iters)
            dis.setVariationalRefinementIterations(var_iters)
            self._dis = dis
        self._ref = None
        self._ref_stats = None

    # -- images ------------------------------------------------------------------
    def _work(self, grey: np.ndarray) -> np.ndarray:
        cv2 = self._cv2
        W, H = self.calib.image_size
        if grey.shape != (H, W):
            raise TacestError(f"frame is {grey.shape[1]}x{grey.shape[0]} px, the calibration says {W}x{H}")
        if grey.dtype != np.uint8:
            grey = np.clip(grey, 0, 255).astype(np.uint8)
        if self.work_size == (W, H):
            return grey
        return cv2.resize(grey, self.work_size, interpolation=cv2.INTER_AREA)

    def set_reference(self, grey: np.ndarray) -> None:
        """Set the no-contact reference frame, (H, W) uint8 grey."""
        self._ref = self._work(grey)
        m, sd = self._cv2.meanStdDev(self._ref, mask=self._work_mask)
        self._ref_stats = (float(m[0, 0]), max(float(sd[0, 0]), 1e-3))

    @property
    def has_reference(self) -> bool:
        return self._ref is not None

    def flow(self, grey: np.ndarray) -> np.ndarray:
        """Dense flow reference -> ``grey`` at the work resolution, (Hw, Ww, 2) float32 in
        work px (component 0 along u)."""
        if self._ref is None:
            raise TacestError("no reference frame set")
        cv2 = self._cv2
        img = self._work(grey)
        if self.settings.match_brightness:
            m, sd = cv2.meanStdDev(img, mask=self._work_mask)
            gain = self._ref_stats[1] / max(float(sd[0, 0]), 1e-3)
            img = cv2.convertScaleAbs(img, alpha=gain, beta=self._ref_stats[0] - gain * float(m[0, 0]))
        if self.settings.method == "dis":
            return self._dis.calc(self._ref, img, None)
        return cv2.calcOpticalFlowFarneback(self._ref, img, None, 0.5, 3, 15, 3, 5, 1.2, 0)

    def coarse_flow(self, flow_work: np.ndarray) -> np.ndarray:
        """Block mean of a work-resolution flow onto the grid, in full-resolution px:
        (Hw, Ww, 2) -> (Hg, Wg, 2)."""
        Hg, Wg = self.grid_shape
        k = self.grid_step
        # INTER_AREA with an integer factor is the exact block mean (5x faster than numpy)
        f = self._cv2.resize(flow_work[: Hg * k, : Wg * k], (Wg, Hg), interpolation=self._cv2.INTER_AREA)
        return f / self.scale_xy

    def analyse(self, grey: np.ndarray, keep_debug: bool = False) -> FrameAnalysis:
        """Analyse one frame (H, W) uint8 grey against the reference."""
        cv2 = self._cv2
        s = self.settings
        fg = self.coarse_flow(self.flow(grey)).astype(float)
        parts = hhd(fg, spacing=self.spacing, mask=self.domain)
        div_c = divergence(parts.curl_free, self.spacing)
        if s.smooth_cells > 0:
            div_c = cv2.GaussianBlur(div_c, (0, 0), s.smooth_cells, borderType=cv2.BORDER_REPLICATE)
        masked = np.where(self.mask, div_c, -np.inf)
        i, j = np.unravel_index(int(np.argmax(masked)), masked.shape)
        peak = float(masked[i, j])
        shear = parts.harmonic[self.mask].mean(axis=0)
        uv = np.full(2, np.nan)
        twist = float("nan")
        if peak > 0:
            region = (masked > s.region_fraction * peak).astype(np.uint8)
            _, labels = cv2.connectedComponents(region, connectivity=8)
            sel = labels == labels[i, j]
            w = masked[sel] - s.region_fraction * peak
            uv = np.array([np.sum(w * self.grid_u[sel]), np.sum(w * self.grid_v[sel])]) / np.sum(w)
            twist = float(np.mean(parts.curl[sel]))
        debug = {}
        if keep_debug:
            debug = {"flow": fg, "hhd": parts, "div_curl_free": div_c}
        return FrameAnalysis(strength=peak, uv=uv, shear=shear, twist=twist, debug=debug)

    def settings_dict(self) -> dict:
        d = asdict(self.settings)
        d["work_size"] = list(self.work_size)
        d["grid_shape"] = [int(self.grid_shape[1]), int(self.grid_shape[0])]  # (width, height)
        d["grid_spacing_px"] = self.spacing
        return d


@dataclass
class ContactDecision:
    """contact : (N,) bool per frame; noise : float, no-contact strength level;
    threshold_on, threshold_off : float, strength thresholds used."""

    contact: np.ndarray
    noise: float
    threshold_on: float
    threshold_off: float


def decide_contacts(strength, settings: DetectSettings | None = None, first_noise_frame: int = 1) -> ContactDecision:
    """Contact flags from per-frame strengths (N,) with hysteresis.

    The noise level is the median strength of frames ``first_noise_frame ..
    first_noise_frame + noise_frames - 1`` (frame 0 is the reference itself when it is the
    first frame, so its strength is ~0 and says nothing about noise).  The median makes one
    odd frame harmless.  Thresholds: on = max(k_on * noise, min_strain), off = max(k_off *
    noise, min_strain * k_off / k_on).
    """
    st = (settings or DetectSettings()).check()
    s = np.nan_to_num(np.asarray(strength, float), nan=0.0, neginf=0.0)
    N = s.shape[0]
    lo = min(first_noise_frame, max(N - 1, 0))
    sample = s[lo: lo + st.noise_frames]
    noise = float(np.median(np.maximum(sample, 0.0))) if sample.size else 0.0
    t_on = max(st.k_on * noise, st.min_strain)
    t_off = max(st.k_off * noise, st.min_strain * st.k_off / st.k_on)
    contact = np.zeros(N, bool)
    on = False
    for k in range(N):
        on = s[k] > (t_off if on else t_on)
        contact[k] = on
    return ContactDecision(contact=contact, noise=noise, threshold_on=t_on, threshold_off=t_off)
