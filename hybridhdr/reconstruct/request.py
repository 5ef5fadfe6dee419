"""One frozen, validated description of a reconstruction run.

:func:`hybridhdr.reconstruct.reconstruct` and :func:`~hybridhdr.reconstruct.reconstruct_iter`
take their many keyword arguments once, check them in :meth:`ReconstructRequest.build` (with the
messages those functions have always raised) and hand the driver one :class:`ReconstructRequest`,
grouped as a reader thinks:

- :class:`RunSettings`: what to run (the method, its parameters, the augmentation, the mode, the
  resolved :class:`Device`, workers and chunking);
- :class:`OutputSettings`: when to output (the output times, or the fps with start and end);
- :class:`ReadSettings`: how to read the recording (the camera profile, a thresholds map given
  by the caller, whether the parameters state thresholds, the frame time offset, the CFA and
  the demosaicker).

Thresholds the recording itself declares are resolved when it is opened
(:func:`hybridhdr.calibrate.resolve.resolve_thresholds`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .._util.limits import check_output_count
from ..calibrate.resolve import (ResolvedThresholds, is_sensor_profile, resolve_thresholds, threshold_arrays,
                                 thresholds_stated)
from .methods import MODES, make_augment_params, make_params, method_spec, resolve_method

__all__ = ["Device", "RunSettings", "OutputSettings", "ReadSettings", "ReconstructRequest", "DEVICES"]

#: The values of ``device``.
DEVICES = ("cpu", "cuda", "auto")


@dataclass(frozen=True)
class Device:
    """Where the filter runs: ``kind`` ("cpu" or "cuda") and the one line saying which and why."""

    kind: str
    line: str

    @classmethod
    def resolve(cls, requested: str, method: str = "akf") -> "Device":
        """The device for a requested one ("cpu", "cuda", "auto") and a method. "cuda" when it
        cannot run raises ValueError; "auto" falls back to the CPU (learned methods choose their
        device through PyTorch, see their params)."""
        if requested not in DEVICES:
            raise ValueError(f"device must be one of {DEVICES}, got {requested!r}")
        if requested == "cpu":
            return cls("cpu", "device: cpu (requested)")
        if not method_spec(method).cuda_engine:
            if requested == "cuda":
                raise ValueError(f"device 'cuda' runs the AKF and the CF family (akf, cf, direct, highpass), not "
                                 f"{method!r} (e2vid/firenet choose their device with their own 'device' parameter)")
            return cls("cpu", f"device: cpu (method {method!r} has no CUDA path here)")
        from .cuda import cuda_unavailable_reason, device_name
        why = cuda_unavailable_reason()
        if why is None:
            return cls("cuda", f"device: cuda ({device_name()})")
        if requested == "cuda":
            raise ValueError(f"device 'cuda' requested but {why}")
        return cls("cpu", f"device: cpu (auto: {why})")

    @property
    def is_cuda(self) -> bool:
        return self.kind == "cuda"

    def naming_engine(self, method: str, mode: str, n_workers: int) -> "Device":
        """This device, its line also naming the CPU engine that runs the AKF (row-band or
        pixel-parallel, by the worker count: :func:`._pixel_engine.engine_line`)."""
        if method != "akf" or self.is_cuda:
            return self
        from ._pixel_engine import engine_line
        return Device(self.kind, self.line + engine_line(method, self.kind, n_workers, mode))


def host_workers(on_gpu: bool, n_workers: int) -> int:
    """Threads for the host-side work around the filter (column split, output collection): the
    ``n_workers`` asked for on the CPU; on the GPU, where the filter needs no host thread, at
    least the machine's cores (up to 16). Thread counts never change a result's bits."""
    n = int(n_workers)
    return n if not on_gpu else max(n, min(os.cpu_count() or 1, 16))


@dataclass(frozen=True, eq=False)
class RunSettings:
    """What to run."""

    method: str
    params: Any  # the method's Params instance
    augment: Any  # AugmentParams
    mode: str
    device: Device
    n_workers: int
    chunk_events: int
    measurements: Any = None
    progress: Callable[[int], None] | None = None

    @property
    def host_workers(self) -> int:
        """Threads for the host side (:func:`host_workers`); learned methods run on the GPU by
        their own ``device`` parameter."""
        on_gpu = self.device.is_cuda or str(getattr(self.params, "device", "cpu")).startswith(("cuda", "auto"))
        return host_workers(on_gpu, self.n_workers)

    @property
    def augmented(self) -> bool:
        """Frame augmentation asked for and possible in this mode (frames still to be checked)."""
        return (self.method == "akf" and self.mode != "causal" and self.measurements is None
                and self.augment.enabled)


@dataclass(frozen=True, eq=False)
class OutputSettings:
    """When to output: ``times_us``, else ``fps`` from ``t_start_us`` (default: the frame times)."""

    times_us: Any = None
    fps: float | None = None
    t_start_us: int | None = None
    t_end_us: int | None = None


@dataclass(frozen=True, eq=False)
class ReadSettings:
    """How to read the recording."""

    profile: Any = None
    thresholds: ResolvedThresholds | None = None  # a map the caller gave (source "map") or a sensor profile ("profile")
    thresholds_stated: bool = False  # the parameters state thresholds: declared ones do not replace them
    frame_time_offset_us: int = 0
    cfa: str | None = None
    demosaic: str = "log_cubic"
    #: the caller's thresholds word: "default" (None given: self-calibrate a recording that
    #: declares none, as the command line's default), "input", "params" or "selfcal" (always)
    choice: str = "default"


def _check_count(name: str, v) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ValueError(f"{name} must be an int >= 1, got {v!r}")


@dataclass(frozen=True, eq=False)
class ReconstructRequest:
    """A validated run: :attr:`run`, :attr:`output`, :attr:`reading` (module docstring)."""

    run: RunSettings
    output: OutputSettings
    reading: ReadSettings

    @classmethod
    def build(cls, method: str = "akf", params=None, *, times_us=None, fps: float | None = None,
              mode: str = "offline", profile=None, t_start_us: int | None = None, t_end_us: int | None = None,
              n_workers: int = 1, chunk_events: int = 1 << 20, measurements=None, progress=None, augment=None,
              thresholds=None, cfa=None, demosaic: str = "log_cubic", frame_time_offset_us: int = 0,
              device: str = "cpu") -> "ReconstructRequest":
        """The request for :func:`~hybridhdr.reconstruct.reconstruct`'s arguments (same meaning),
        checked in the order and with the messages that function raises."""
        method = resolve_method(method)
        dev = Device.resolve(device, method)
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        _check_count("n_workers", n_workers)
        _check_count("chunk_events", chunk_events)
        dev = dev.naming_engine(method, mode, int(n_workers))
        for name, v in (("t_start_us", t_start_us), ("t_end_us", t_end_us)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))):
                raise TypeError(f"{name} must be an int (µs) or None, got {type(v).__name__}")
        p = make_params(method, params)
        aug = make_augment_params(augment)
        choice = "default"
        if isinstance(thresholds, str) and thresholds in ("input", "params", "selfcal"):
            choice, thresholds = thresholds, None
        if isinstance(thresholds, ResolvedThresholds):
            # already resolved by the caller (calibrate.resolve): used as it is
            given, choice = thresholds, ("profile" if thresholds.source == "profile" else "map")
        elif is_sensor_profile(thresholds):
            # a sensor profile file (calibrate sensor): its values are used as they are, no estimation;
            # the AKF takes its log offset I0 too, a method with its own log model keeps its own
            own_i0 = None if method == "akf" else getattr(p, "intensity_offset", 0.0)
            given = resolve_thresholds(None, thresholds, intensity_offset=own_i0)
            choice = "profile"
        else:
            given = None if thresholds is None else ResolvedThresholds("map", maps=threshold_arrays(thresholds))
        if times_us is not None:
            check_output_count(int(np.size(times_us)))  # before any work (docs/security.md)
        if isinstance(frame_time_offset_us, bool) or not isinstance(frame_time_offset_us, (int, np.integer)):
            raise TypeError(f"frame_time_offset_us must be an int (µs), got {type(frame_time_offset_us).__name__}")
        run = RunSettings(method, p, aug, mode, dev, int(n_workers), int(chunk_events), measurements, progress)
        out = OutputSettings(times_us, fps, t_start_us, t_end_us)
        read = ReadSettings(profile, given, thresholds_stated(params), int(frame_time_offset_us), cfa, demosaic,
                            choice if choice == "profile" else ("map" if given is not None else choice))
        return cls(run, out, read)
