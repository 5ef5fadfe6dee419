"""Parameters of the reconstruction methods: frozen, keyword-only dataclasses with units in names.

Each class validates itself in ``__post_init__``, loads from a dict or a TOML file
(``from_dict`` / ``from_toml``), and offers presets as named constructors.

References
----------
Z. Wang, Y. Ng, C. Scheerlinck, R. Mahony, "An Asynchronous Kalman Filter for Hybrid Event
Cameras", ICCV 2021, doi:10.1109/ICCV48922.2021.00050 (defaults: §6; table in
``ziweiWWANG/AKF:run_akf.m``).
C. Scheerlinck, N. Barnes, R. Mahony, "Continuous-time Intensity Estimation Using Event
Cameras", ACCV 2018, doi:10.1007/978-3-030-20873-8_20 (CF, high-pass filter).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .._util.toml import load_toml
from ..camera.encoding import DEFAULT_INTENSITY_OFFSET

__all__ = ["AKFParams", "CFParams", "HighPassParams", "DirectParams", "FramesParams",
           "DEFAULT_INTENSITY_OFFSET"]

#: I0 of the published code (``ziweiWWANG/AKF``: log(I^F/255 + 1)) and of CF's ROS code.
PUBLISHED_INTENSITY_OFFSET = 1.0


class _ParamsMixin:
    """from_dict / from_toml / to_dict / replace for the frozen parameter dataclasses."""

    _toml_table: str = ""

    @classmethod
    def from_dict(cls, d: dict):
        """Build from a mapping of field names; unknown names raise ``ValueError``."""
        if not isinstance(d, dict):
            raise TypeError(f"{cls.__name__}.from_dict expects a dict, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown {cls.__name__} parameter(s) {unknown}; expected some of {sorted(names)}")
        return cls(**d)

    @classmethod
    def from_toml(cls, path):
        """Read a TOML file: either top-level keys or a table named after the method
        (``[akf]``, ``[cf]``, ``[highpass]``, ``[direct]``, ``[frames]``)."""
        d = load_toml(path)
        if cls._toml_table in d and isinstance(d[cls._toml_table], dict):
            d = d[cls._toml_table]
        d = {k: v for k, v in d.items() if not isinstance(v, dict)}
        return cls.from_dict(d)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def replace(self, **changes):
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    # -- validation helpers ---------------------------------------------------------------------
    def _num(self, name: str, *, lo=None, lo_open=False, hi=None, allow_none=False):
        v = getattr(self, name)
        if v is None and allow_none:
            return
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError(f"{type(self).__name__}.{name} must be a number, got {type(v).__name__} {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"{type(self).__name__}.{name} must be finite, got {v}")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise ValueError(f"{type(self).__name__}.{name} must be {'>' if lo_open else '>='} {lo}, got {v}")
        if hi is not None and v > hi:
            raise ValueError(f"{type(self).__name__}.{name} must be <= {hi}, got {v}")
        object.__setattr__(self, name, v)

    def _choice(self, name: str, choices):
        v = getattr(self, name)
        if v not in choices:
            raise ValueError(f"{type(self).__name__}.{name} must be one of {list(choices)}, got {v!r}")

    def _bool(self, name: str):
        v = getattr(self, name)
        if not isinstance(v, bool):
            raise TypeError(f"{type(self).__name__}.{name} must be a bool, got {type(v).__name__} {v!r}")

    def _threshold_search(self):
        """The fields of a contrast-threshold search (EDI, augmentation): ``contrast_threshold`` > 0
        or None, 0 < ``threshold_min`` < ``threshold_max``, ``tv_weight`` >= 0."""
        self._num("contrast_threshold", lo=0, lo_open=True, allow_none=True)
        self._num("threshold_min", lo=0, lo_open=True)
        self._num("threshold_max", lo=0, lo_open=True)
        if self.threshold_min >= self.threshold_max:
            raise ValueError(f"{type(self).__name__}.threshold_min ({self.threshold_min}) must be below "
                             f"threshold_max ({self.threshold_max})")
        self._num("tv_weight", lo=0)


class _ThresholdMixin:
    @property
    def c_on(self) -> float:
        """ON contrast threshold in natural-log units."""
        return self.contrast_threshold if self.contrast_threshold_on is None else self.contrast_threshold_on

    @property
    def c_off(self) -> float:
        """OFF contrast threshold (positive) in natural-log units."""
        return self.contrast_threshold if self.contrast_threshold_off is None else self.contrast_threshold_off

    def _check_thresholds(self):
        self._num("contrast_threshold", lo=0, lo_open=True)
        self._num("contrast_threshold_on", lo=0, lo_open=True, allow_none=True)
        self._num("contrast_threshold_off", lo=0, lo_open=True, allow_none=True)


@dataclass(frozen=True, kw_only=True)
class AKFParams(_ParamsMixin, _ThresholdMixin):
    """Parameters of the Asynchronous Kalman Filter (Wang et al., ICCV 2021).

    Defaults are the paper's (§6) where it gives values, else the reference code's
    (``ziweiWWANG/AKF:run_akf.m``). Rates are per second.

    Parameters
    ----------
    contrast_threshold : float
        Event contrast threshold c in natural-log units (eq. 1); the paper gives none, the
        reference code's comments use 0.1.
    contrast_threshold_on, contrast_threshold_off : float or None
        Separate ON / OFF thresholds (positive, log units); ``None`` means ``contrast_threshold``.
    process_noise_per_s : float
        σ²_proc in log²/s (§3.1.1; paper §6: 5e-4, kept by :meth:`paper`). Ours is 0.05: the
        sub-threshold change no event reports grows the uncertainty between frames, so that the
        discrete frame update trusts a new frame over a state last corrected a frame period ago
        (edge sweep of ``benchmarks/accuracy.py``: well-exposed log error 0.017 → 0.007,
        ecd_slider_depth held-out frames unchanged within 0.5 %). With :attr:`noise_from_frames`
        the value measured on the input replaces it where the frames identify it.
    isolated_noise_per_s : float
        σ²_iso in log²/s (§3.1.1; paper §6: 0.03).
    refractory_noise : float
        σ²_ref: log² (paper form, §6: 0.01) or log²/s (reference form).
    refractory_period_us : int
        ρ, the refractory-period bound in µs (§3.1.1 gives none; reference code 10 000 µs).
    noise_model : {"paper", "reference_code"}
        Form of Q (Wang et al. 2021, §3): the paper's (time since the previous event for Q_proc, constant
        Q_ref) or the reference code's (time since the last update, Q_ref ∝ interval).
    initial_covariance : float
        P at initialisation from the first frame, log² (§6: "initialised to 0.01").
    intensity_offset : float
        I0 of eq. 8, in scaled-irradiance units (brightest code = 1).
    bias_correction : bool
        Subtract R/2 from log(I + I0) (eq. 8). Off in our model: with a small I0, R = R̄/(I + I0)²
        of a dark code is far outside the small-variance expansion behind eq. 8 (R ≈ 12 at gamma
        code 5), and the correction drives static dark pixels 46-99 % below their intensity;
        :meth:`paper` keeps it.
    covariance_interpolation : {"linear", "hold"}
        R between frames: eq. 7's linear interpolation (exactly integrated; offline mode only)
        or held at the frame's value.
    frame_precision_scale : float or None
        Overrides the camera profile's 1/σ²_im (eq. 6; §6: 7e5 DAVIS240C, 7e7 FLIR). With
        :attr:`noise_from_frames` the value measured on the input replaces it where the frames
        identify it.
    saturation : {"bound", "value"}
        "bound" (ours): a clipped frame code is a censored measurement, "at least the clip
        level" (or "at most the dark level"), acting only when the state violates it, so a
        bright object tracked by events is not pulled down to the clip value; "value": the
        paper's reading, the clipped code as a (floored-weight) measurement of that value.
    min_weighting : float or None
        Overrides the camera profile's floor on f_w (eq. 6's saturation; reference code 0.09).
    censored_initial_covariance : float
        P at initialisation of a pixel the first frame clips bright, log²: it is known only to
        lie beyond the bound (1e3: unknown), so a later unclipped frame or the other pass of the
        two-sided filter decides its value; a bound moves L̂ but never shrinks P. A pixel the
        first frame clips dark is bounded on both sides (the state is ln(I + I0) with I >= 0, so
        ln I0 <= L <= L_dark): its P is (L_dark - ln I0)², at least ``initial_covariance``.
    frame_update : {"discrete", "continuous"}
        "discrete" (ours): each frame is also applied at τ_k as one discrete Kalman measurement
        (gain P/(P + R), R of eq. 9; a continuous-discrete Kalman filter), so the estimate at a
        frame time holds that frame's information; the continuous pull of eqs. 14-20 then
        continues. "continuous": the paper's, the frame acts only through the pull after τ_k.
    event_interpolation : bool
        Without frame augmentation (causal mode, or ``augment=False``): carry each frame forward
        with the events since it (L^A steps by the nominal threshold at each event; eq. 10's
        forward interpolation without deblurring or calibration, causal). False: the paper's
        zero-order hold, which pulls an edge that arrives between frames back to the old frame.
    fusion_carried_variance : bool
        Two-sided (offline) mode only, ours: each pass is fused with its P plus the variance its
        carried frame has accumulated since that frame, σ²_ref (the paper form's per-event value;
        0.01 with the reference-code noise form) per event and σ²_proc per second
        (``docs/reconstruct.md``, "Two-sided AKF"). The continuous pull towards L^A keeps P near R
        whatever the frame's age, so fused on P alone an estimate carried 45 ms weighs as much as
        one carried 5 ms. False: P alone (the presets, which have no two-sided filter to follow).
    exposure_mean : bool
        Ours: where the frames stamp an exposure ``[s_k, e_k)`` (AEDAT4, the container, the
        simulator), read each frame as the mean of the intensity over its exposure, as EDI does
        (Pan et al., CVPR 2019; the paper's §4.1 deblurring), and correct L^F by the events inside
        it to the latent image at mid-exposure τ_k
        (:func:`~hybridhdr.reconstruct.edi.exposure_log_corrections`; pixels without events in
        the exposure are unchanged). The events are then held in memory. False: the frame is
        the intensity at τ_k (the paper's model). Without frame augmentation only (the
        augmentation deblurs its frames itself).
    exposure_min_events : int or None
        With ``exposure_mean``, correct a pixel only when at least this many events fell in the
        exposure; None (default): frame augmentation's ``n* = ceil(sqrt(24 / (√12 c)))`` for the
        smaller of the ON/OFF thresholds (6 at c = 0.2, 9 at c = 0.1), below which each event's
        quantisation (about c/√12) costs more than the blur it removes (about Δ²/24 for a log
        change Δ over the exposure; :class:`~hybridhdr.reconstruct.augment.AugmentParams`); 0:
        every pixel with an event.
    noise_from_frames : bool
        Ours, opt-in: measure the frames' noise σ²_im (eq. 6's scale, ``frame_precision_scale``)
        and the process noise σ²_proc (``process_noise_per_s``) on the input's own frames, at the
        pixels without events (the local level model's moments,
        :func:`hybridhdr.calibrate.frame_noise.estimate_frame_noise`), and use them in place of
        these two fields where they are left at their defaults (``frame_precision_scale`` None,
        ``process_noise_per_s`` 0.05: a value you state wins) and the frames identify them (the
        run's ``info["frame_noise"]["applied"]`` says which). Their ratio decides how many past
        frames the filter averages where no event reports a change: the paper's DAVIS240C
        precision (7e5) is 23-108x the one measured on the two real recordings and σ²_proc 0.05
        is 10-50x their drift, so by default the filter restarts from each new frame and passes
        the frames' temporal noise to the output. On held-out frames it lowers the causal AKF's
        MSE 16 % on ``davis346_street``; it is off by default because, with the event noise
        terms (σ²_ref, σ²_iso) left at the paper's values, it raises the over-exposed x4
        recoverable error (``docs/reconstruct.md``, "Frame noise measured on the recording").
        The two-sided fusion's carried variance keeps its rate (``fusion_carried_rate_per_s``).
    fusion_carried_rate_per_s : float or None
        The per-second rate of :attr:`fusion_carried_variance`, log²/s; None: ``process_noise_per_s``.
        :attr:`noise_from_frames` sets it to ``process_noise_per_s``'s value before measuring: the
        drift measured where no event fired says nothing of how fast an estimate carried by events
        from a frame loses track (threshold errors, missed events), which is what the fusion
        weighs (on ``ecd_slider_depth`` the measured drift as this rate raised the two-sided
        held-out MSE 5.89e-3 → 6.63e-3).
    """

    _toml_table = "akf"

    contrast_threshold: float = 0.1  # c, log units; reference-code comments (``ziweiWWANG/AKF:run_akf.m``)
    contrast_threshold_on: float | None = None
    contrast_threshold_off: float | None = None
    process_noise_per_s: float = 0.05  # σ²_proc; paper §6: 5e-4 (see the docstring)
    isolated_noise_per_s: float = 0.03  # σ²_iso, paper §6
    refractory_noise: float = 0.01  # σ²_ref, paper §6
    refractory_period_us: int = 10_000  # ρ, reference code run_akf.m
    noise_model: str = "paper"  # eq. 2 / §3.1.1
    initial_covariance: float = 0.01  # paper §6 "initialised to 0.01"
    intensity_offset: float = DEFAULT_INTENSITY_OFFSET  # I0, eq. 8 (no value in the paper)
    bias_correction: bool = False  # eq. 8 (paper: True; see the docstring)
    covariance_interpolation: str = "linear"  # eq. 7
    frame_precision_scale: float | None = None  # 1/σ²_im, eq. 6 (None: from the profile)
    saturation: str = "bound"  # ours; the paper's reading is "value"
    min_weighting: float | None = None  # eq. 6's floor on f_w (None: from the profile)
    censored_initial_covariance: float = 1e3  # ours, log²: unknown beyond the bound
    frame_update: str = "discrete"  # ours; the paper's is "continuous"
    event_interpolation: bool = True  # ours; the paper holds frames (zero-order)
    fusion_carried_variance: bool = True  # ours (two-sided mode)
    exposure_mean: bool = True  # ours: a frame is the mean over its exposure (EDI's model)
    exposure_min_events: int | None = None  # None: n* from c (as frame augmentation's deblurring)
    noise_from_frames: bool = False  # ours, opt-in: σ²_im and σ²_proc measured on the input's frames
    fusion_carried_rate_per_s: float | None = None  # None: process_noise_per_s

    def __post_init__(self):
        self._check_thresholds()
        self._num("process_noise_per_s", lo=0)
        self._num("isolated_noise_per_s", lo=0)
        self._num("refractory_noise", lo=0)
        v = self.refractory_period_us
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"AKFParams.refractory_period_us must be an int >= 0 µs, got {v!r}")
        self._choice("noise_model", ("paper", "reference_code"))
        self._num("initial_covariance", lo=0, lo_open=True)
        self._num("intensity_offset", lo=0, lo_open=True)
        self._bool("bias_correction")
        self._choice("covariance_interpolation", ("linear", "hold"))
        self._num("frame_precision_scale", lo=0, lo_open=True, allow_none=True)
        self._choice("saturation", ("bound", "value"))
        self._num("min_weighting", lo=0, lo_open=True, hi=1, allow_none=True)
        self._bool("event_interpolation")
        self._bool("fusion_carried_variance")
        self._bool("exposure_mean")
        self._bool("noise_from_frames")
        self._num("fusion_carried_rate_per_s", lo=0, allow_none=True)
        v = self.exposure_min_events
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
            raise ValueError(f"AKFParams.exposure_min_events must be None or an int >= 0, got {v!r}")
        self._choice("frame_update", ("discrete", "continuous"))
        self._num("censored_initial_covariance", lo=0, lo_open=True)

    @classmethod
    def default(cls, **overrides) -> "AKFParams":
        """hybridhdr's model (the defaults): the paper's §6 noise settings with a small I0 in
        frame-linear units and saturated codes as bounds."""
        return cls(**overrides)

    def carried_variance(self) -> tuple[float, float] | None:
        """``(q per event, s per second)`` of :attr:`fusion_carried_variance`, or None when off."""
        if not self.fusion_carried_variance:
            return None
        q = self.refractory_noise if self.noise_model == "paper" else 0.01
        rate = self.process_noise_per_s if self.fusion_carried_rate_per_s is None else self.fusion_carried_rate_per_s
        return float(q), float(rate)

    @classmethod
    def paper(cls, **overrides) -> "AKFParams":
        """The paper's §6 settings, with its reading of the frames: I0 = 1 as in the published
        code (the paper gives no value) and clipped codes as values."""
        d = dict(process_noise_per_s=5e-4, intensity_offset=PUBLISHED_INTENSITY_OFFSET, saturation="value",
                 bias_correction=True,
                 event_interpolation=False,
                 frame_update="continuous", fusion_carried_variance=False, exposure_mean=False,
                 noise_from_frames=False)
        d.update(overrides)
        return cls(**d)

    @classmethod
    def reference_code(cls, **overrides) -> "AKFParams":
        """Settings of ``ziweiWWANG/AKF:run_akf.m``: σ_p 5e-3, σ_r 0.05 (per s),
        p_ini 0.09, I0 = 1, no eq. 8 correction, reference-code noise form, clipped codes as values."""
        d = dict(process_noise_per_s=5e-3, isolated_noise_per_s=0.03, refractory_noise=0.05,
                 refractory_period_us=10_000, noise_model="reference_code", initial_covariance=0.09,
                 intensity_offset=PUBLISHED_INTENSITY_OFFSET, bias_correction=False, saturation="value",
                 event_interpolation=False, frame_update="continuous", fusion_carried_variance=False,
                 exposure_mean=False, noise_from_frames=False)
        d.update(overrides)
        return cls(**d)


@dataclass(frozen=True, kw_only=True)
class CFParams(_ParamsMixin, _ThresholdMixin):
    """Complementary filter (Scheerlinck et al., ACCV 2018): dL̂/dt = e - α(L̂ - L^F).

    Parameters
    ----------
    cutoff_hz : float
        Crossover frequency f_c in Hz; α = 2π f_c rad/s (the ROS implementation,
        ``cedric-scheerlinck/dvs_image_reconstruction``, reads its default 0.5 Hz → α = π rad/s).
        0 integrates events without frame correction.
    contrast_threshold, contrast_threshold_on, contrast_threshold_off : float
        As in :class:`AKFParams` (log units; 0.1 in the ROS implementation).
    intensity_offset : float
        Offset in L^F = log(I + I0), frame-linear units; default 1, the published CF's
        log(I^F/255 + 1) (the AKF's own model uses 1e-3, ``AKFParams``). Estimates that fall
        below 0 are clamped and counted like every method's.
    adaptive_gain : bool
        Per-pixel HDR-adaptive gain: α is multiplied by ``adaptive_gain_scale`` where the frame
        is under- or over-exposed (I outside [``adaptive_low``, ``adaptive_high``]), so that
        events dominate there (ACCV 2018, adaptive gain; the exact published form is not
        verified here).
    adaptive_gain_scale : float
        Factor on α at badly exposed pixels, in [0, 1].
    adaptive_low, adaptive_high : float
        Well-exposed range of the scaled irradiance I (0..1).
    """

    _toml_table = "cf"

    cutoff_hz: float = 0.5
    contrast_threshold: float = 0.1
    contrast_threshold_on: float | None = None
    contrast_threshold_off: float | None = None
    intensity_offset: float = PUBLISHED_INTENSITY_OFFSET  # the published CF / direct integration: log(I + 1)
    adaptive_gain: bool = False
    adaptive_gain_scale: float = 0.1
    adaptive_low: float = 0.05
    adaptive_high: float = 0.95

    def __post_init__(self):
        self._check_thresholds()
        self._num("cutoff_hz", lo=0)
        self._num("intensity_offset", lo=0, lo_open=True)
        self._bool("adaptive_gain")
        self._num("adaptive_gain_scale", lo=0, hi=1)
        self._num("adaptive_low", lo=0, hi=1)
        self._num("adaptive_high", lo=0, hi=1)
        if self.adaptive_low >= self.adaptive_high:
            raise ValueError(f"CFParams.adaptive_low ({self.adaptive_low}) must be below "
                             f"adaptive_high ({self.adaptive_high})")

    @property
    def alpha_rad_per_s(self) -> float:
        """α = 2π·cutoff_hz in rad/s."""
        return 2.0 * math.pi * self.cutoff_hz

    @classmethod
    def fixed(cls, **overrides) -> "CFParams":
        """Fixed gain, the ROS implementation's defaults (0.5 Hz, c = 0.1)."""
        return cls(**overrides)

    @classmethod
    def adaptive(cls, **overrides) -> "CFParams":
        """HDR-adaptive per-pixel gain."""
        overrides.setdefault("adaptive_gain", True)
        return cls(**overrides)


@dataclass(frozen=True, kw_only=True)
class HighPassParams(_ParamsMixin, _ThresholdMixin):
    """High-pass filter on events only: the CF with L^F = 0 (AKF paper §2; ACCV 2018).

    Output is the relative intensity exp(L̂) (1 = unchanged since the start).

    Parameters
    ----------
    cutoff_hz : float
        f_c in Hz, α = 2π f_c (0.06 Hz in ``dvs_image_reconstruction``'s ``pure_event_reconstruction``).
    event_decay : float
        Extra dimensionless decay exp(-event_decay) of L̂ at each event (the ROS code's α_e,
        0.06 there; 0 by default, the pure high-pass filter).
    """

    _toml_table = "highpass"

    cutoff_hz: float = 0.06
    contrast_threshold: float = 0.1
    contrast_threshold_on: float | None = None
    contrast_threshold_off: float | None = None
    event_decay: float = 0.0

    def __post_init__(self):
        self._check_thresholds()
        self._num("cutoff_hz", lo=0)
        self._num("event_decay", lo=0)

    @property
    def alpha_rad_per_s(self) -> float:
        return 2.0 * math.pi * self.cutoff_hz


@dataclass(frozen=True, kw_only=True)
class DirectParams(_ParamsMixin, _ThresholdMixin):
    """Direct integration: L̂ = log(I_k + I0) + Σσc since the last frame (Brandli et al. 2014)."""

    _toml_table = "direct"

    contrast_threshold: float = 0.1
    contrast_threshold_on: float | None = None
    contrast_threshold_off: float | None = None
    intensity_offset: float = PUBLISHED_INTENSITY_OFFSET  # the published CF / direct integration: log(I + 1)

    def __post_init__(self):
        self._check_thresholds()
        self._num("intensity_offset", lo=0, lo_open=True)


@dataclass(frozen=True, kw_only=True)
class FramesParams(_ParamsMixin):
    """Frames only: ``interpolation`` "zoh" (zero-order hold) or "linear" (in linear intensity)."""

    _toml_table = "frames"

    interpolation: str = "zoh"

    def __post_init__(self):
        self._choice("interpolation", ("zoh", "linear"))
