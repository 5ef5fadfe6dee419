"""The reconstruction methods by name, with what each one can do (:class:`MethodSpec`), and the
parsing of their parameters and of the AKF's frame augmentation.

One registry serves the API, the command line, the GPU path, ``evaluate`` and the benchmarks:
a method's capabilities are named fields here, not positions in a tuple or lists repeated
across modules. Importing it imports no kernel (the command line builds its parser from it):
a method's parameter class is imported when it is first asked for.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass

__all__ = ["MethodSpec", "METHODS", "METHOD_ALIASES", "MODES", "method_spec", "resolve_method", "make_params",
           "make_augment_params", "methods_with"]

#: The filter modes (``reconstruct(mode=...)``).
MODES = ("offline", "causal", "forward")


@dataclass(frozen=True)
class MethodSpec:
    """What a reconstruction method is and can do.

    Attributes
    ----------
    name : str
    params_ref : str
        ``"module:Class"`` (relative to :mod:`hybridhdr.reconstruct`) of its ``…Params``
        dataclass, :attr:`params_class`.
    needs_frames : bool
        It cannot run without frames (else: events only).
    uses_events : bool
        It reads events (else: frames only).
    takes_thresholds : bool
        Its events are scaled by contrast thresholds (scalar ON/OFF in its parameters, or a
        per-pixel map): the thresholds resolver applies to it.
    cuda_engine : bool
        It has an engine on the GPU (:mod:`hybridhdr.reconstruct.cuda`).
    description : str
        One line for ``--help``, ``run.json`` and reports.
    """

    name: str
    params_ref: str
    needs_frames: bool
    uses_events: bool
    takes_thresholds: bool
    cuda_engine: bool
    description: str

    @property
    def params_class(self) -> type:
        """The method's ``…Params`` dataclass (imported on first use)."""
        mod, _, cls = self.params_ref.partition(":")
        return getattr(importlib.import_module(mod, __package__), cls)

    @property
    def frames_only(self) -> bool:
        return not self.uses_events

    @property
    def events_only(self) -> bool:
        return not self.needs_frames


def _spec(name, cls, frames, events, thresholds, cuda, description) -> tuple[str, MethodSpec]:
    return name, MethodSpec(name, cls, frames, events, thresholds, cuda, description)


#: method name -> :class:`MethodSpec`
METHODS: dict[str, MethodSpec] = dict([
    _spec("akf", ".params:AKFParams", True, True, True, True, "Asynchronous Kalman Filter (Wang et al., ICCV 2021)"),
    _spec("cf", ".params:CFParams", True, True, True, True,
          "complementary filter, fixed or HDR-adaptive gain (Scheerlinck et al., ACCV 2018)"),
    _spec("highpass", ".params:HighPassParams", False, True, True, True,
          "high-pass filter on events only (CF with zero frame input)"),
    _spec("direct", ".params:DirectParams", True, True, True, True, "direct integration of events onto the last frame"),
    _spec("frames_zoh", ".params:FramesParams", True, False, False, False, "frames only, zero-order hold"),
    _spec("frames_linear", ".params:FramesParams", True, False, False, False, "frames only, linear interpolation in intensity"),
    _spec("edi", ".edi:EDIParams", True, True, False, False,
          "EDI deblurring: high-rate video from each blurred frame and its events (Pan et al., CVPR 2019)"),
    _spec("e2vid", ".learned.params:E2VIDParams", False, True, False, False,
          "E2VID recurrent UNet on event voxel grids, events only, released weights (Rebecq et al., TPAMI 2019)"),
    _spec("firenet", ".learned.params:FireNetParams", False, True, False, False,
          "FireNet light recurrent network, events only, released weights (Scheerlinck et al., WACV 2020)"),
])
METHOD_ALIASES = {"hpf": "highpass", "frames": "frames_zoh"}


def methods_with(**capabilities) -> tuple[str, ...]:
    """The method names whose :class:`MethodSpec` has every given capability, in registry order,
    e.g. ``methods_with(cuda_engine=True)``."""
    return tuple(n for n, s in METHODS.items() if all(getattr(s, k) == v for k, v in capabilities.items()))


def resolve_method(method: str) -> str:
    """The registry name of ``method`` (an alias resolved); ValueError for an unknown one."""
    if not isinstance(method, str):
        raise TypeError(f"method must be a str, got {type(method).__name__}")
    m = METHOD_ALIASES.get(method, method)
    if m not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {sorted(METHODS) + sorted(METHOD_ALIASES)}")
    return m


def method_spec(method: str) -> MethodSpec:
    """The :class:`MethodSpec` of a method name or alias."""
    return METHODS[resolve_method(method)]


def make_params(method: str, params=None):
    """Params for ``method`` from None (defaults), a dict, a TOML path or a Params instance."""
    method = resolve_method(method)
    cls = METHODS[method].params_class
    if params is None:
        p = cls()
    elif isinstance(params, cls):
        p = params
    elif isinstance(params, dict):
        p = cls.from_dict(params)
    elif isinstance(params, (str, os.PathLike)):
        p = cls.from_toml(params)
    else:
        raise TypeError(f"params for method {method!r} must be {cls.__name__}, a dict, a TOML path or None, "
                        f"got {type(params).__name__}")
    if method == "frames_linear" and p.interpolation != "linear":
        p = p.replace(interpolation="linear")
    if method == "frames_zoh" and p.interpolation != "zoh":
        p = p.replace(interpolation="zoh")
    return p


def make_augment_params(augment):
    """AugmentParams from None/True (defaults), False (off), a dict, a TOML path or an instance."""
    from .augment import AugmentParams
    if augment is None:
        return AugmentParams()  # off: the default measurement carries frames forward with events
    if augment is True:
        return AugmentParams(enabled=True)
    if augment is False:
        return AugmentParams.off()
    if isinstance(augment, AugmentParams):
        return augment
    if isinstance(augment, dict):
        return AugmentParams.from_dict({"enabled": True, **augment})
    if isinstance(augment, (str, os.PathLike)):
        from .._util.toml import load_toml
        d = load_toml(augment)
        d = d["augment"] if isinstance(d.get("augment"), dict) else d
        return AugmentParams.from_dict({"enabled": True, **{k: v for k, v in d.items() if not isinstance(v, dict)}})
    raise TypeError(f"augment must be AugmentParams, a dict, a TOML path, a bool or None, "
                    f"got {type(augment).__name__}")
