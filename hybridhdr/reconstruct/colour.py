"""Colour event cameras: every method on the Bayer mosaic, demosaicked outputs.

A colour event camera (DAVIS346 colour, Color-DAVIS, ...) puts a Bayer filter over the event
pixels, so each event reports a change of log intensity of *one* colour: the colour its pixel's
filter passes. A frame sensor behind the same filter (the DAVIS APS shares the pixels) measures
that same colour at that pixel. So the AKF, and every baseline (CF, high-pass, direct
integration, frames only, EDI), is the monochrome filter run unchanged on the raw mosaic:

1. **Frames to the mosaic** (:func:`hybridhdr.camera.cfa.mosaic_frames`). RGB frames
   (K, H, W, 3), e.g. demosaicked by the camera driver, give each pixel the code of its own
   channel (the encodings act per channel, so the channel's code is decoded by the same camera
   profile as a grey code; integer frames keep the AKF's look-up tables). Grey frames declared
   as the same mosaic are used as they are. Each event pixel is thus filtered against the frame
   value of its own colour, never against luminance.
2. **Every method unchanged**, on the mosaic of events and frames.
3. **Outputs demosaicked** (:func:`hybridhdr.camera.cfa.demosaic`, ``"log_cubic"`` by default,
   ``"log_bilinear"``, ``"bilinear"`` and ``"edge_aware"`` selectable) to linear RGB, float32 (K, H, W, 3); each pixel's own channel
   is the filter's estimate, bit for bit. :meth:`Video.luminance` gives Rec. 709 luminance for
   the metrics.

The pattern comes from the recording (``metadata.event_camera.cfa``; the frame camera's
``metadata.frame_camera.cfa`` says whether grey frames are a raw mosaic), or from ``cfa=``
(``--cfa``), which sets both, or ``"none"`` to force the monochrome path. With no pattern
anywhere nothing here runs: monochrome results are those of the monochrome code, bit for bit.

Limits: the AKF's isolated-pixel noise term (§3.1.1) looks at the 3×3 neighbours' event times,
which on a mosaic belong to the other colours (an edge moves through all of them, so the cue
holds for motion); EDI's threshold search scores sharpness on the mosaic, where a saturated
colour is a 2-pixel texture.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ..camera.cfa import DEMOSAIC_METHODS, demosaic, mosaic_frames, parse_cfa
from ..camera.encoding import LUMINANCE_WEIGHTS
from ..model import Recording, source_metadata

__all__ = ["ColourSource", "colour_source", "source_cfa", "rgb_to_luminance"]




def source_cfa(source, cfa=None) -> tuple[str | None, str | None]:
    """``(event pattern, frame pattern)`` of a source: ``cfa`` when given (it sets both; "none"
    forces monochrome), else what its metadata declares."""
    if cfa is not None:
        p = parse_cfa(cfa)
        return p, p
    md = source_metadata(source)
    ev = getattr(getattr(md, "event_camera", None), "cfa", None)
    fr = getattr(getattr(md, "frame_camera", None), "cfa", None)
    return parse_cfa(ev), parse_cfa(fr)


class _MosaicReader:
    """A reader whose frames are the event sensor's mosaic; everything else is the reader's."""

    def __init__(self, reader, frames):
        self._reader = reader
        self._frames = frames

    def __getattr__(self, name):
        return getattr(self._reader, name)

    def read_frames(self):
        return self._frames


class ColourSource:
    """The mosaic view of a colour source and the demosaicking of its outputs.

    Use :func:`colour_source`, which returns None for a monochrome source.
    """

    def __init__(self, source, pattern: str, frame_pattern: str | None, demosaic_method: str = "log_cubic"):
        if demosaic_method not in DEMOSAIC_METHODS:
            raise ValueError(f"demosaic must be one of {DEMOSAIC_METHODS}, got {demosaic_method!r}")
        self.pattern = pattern
        self.demosaic_method = demosaic_method
        self._close = None
        if isinstance(source, Recording):
            frames = source.frames
            self.frames_note = self._note(frames, frame_pattern)
            if frames is not None and len(frames):
                frames = mosaic_frames(frames, pattern, frame_pattern)
            self.source = dataclasses.replace(source, frames=frames)
            return
        reader = source
        if isinstance(source, (str, os.PathLike)):
            from ..formats import open_reader
            reader = open_reader(source)
            self._close = reader.close
        try:
            frames = reader.read_frames() if hasattr(reader, "read_frames") else None
            self.frames_note = self._note(frames, frame_pattern)
            if frames is not None and len(frames):
                frames = mosaic_frames(frames, pattern, frame_pattern)
        except BaseException:
            self.close()
            raise
        self.source = _MosaicReader(reader, frames)

    def _note(self, frames, frame_pattern) -> str:
        if frames is None or len(frames) == 0:
            return "no frames"
        if frames.images.ndim == 4:
            return f"RGB frames, each pixel's {self.pattern} channel"
        if parse_cfa(frame_pattern) == self.pattern:
            return f"raw {self.pattern} mosaic frames"
        return f"raw {frame_pattern} mosaic frames, demosaicked (bilinear) and re-mosaicked to {self.pattern}"

    def close(self):
        if self._close is not None:
            self._close()
            self._close = None

    def info(self) -> dict:
        return {"event": self.pattern, "frames": self.frames_note, "demosaic": self.demosaic_method}

    def demosaic_outputs(self, pairs, info: dict | None = None):
        """``(t_us, (H, W) mosaic)`` pairs -> ``(t_us, (H, W, 3) linear RGB float32)``; ``info``
        (the run statistics) gains ``cfa``."""
        try:
            for t, img in pairs:
                yield t, demosaic(img, self.pattern, self.demosaic_method)
            if info is not None:
                info["cfa"] = self.info()
        finally:
            self.close()


def colour_source(source, cfa=None, demosaic_method: str = "log_cubic") -> ColourSource | None:
    """A :class:`ColourSource` when the source (or ``cfa``) has a Bayer pattern, else None.

    Parameters
    ----------
    source : Recording, reader, RecordingFile or path
    cfa : str or None
        None: the recording's own ``metadata.event_camera.cfa`` (and ``frame_camera.cfa``);
        a pattern (``RGGB``, ``BGGR``, ``GRBG``, ``GBRG``) sets both; ``"none"`` forces the
        monochrome path.
    demosaic_method : {"log_cubic", "log_bilinear", "bilinear", "edge_aware"}
    """
    if demosaic_method not in DEMOSAIC_METHODS:
        raise ValueError(f"demosaic must be one of {DEMOSAIC_METHODS}, got {demosaic_method!r}")
    if cfa is None and isinstance(source, (str, os.PathLike)):
        from ..formats import open_reader
        reader = open_reader(source)
        try:
            pattern, frame_pattern = source_cfa(reader)
        except BaseException:
            reader.close()
            raise
        if pattern is None:
            reader.close()
            return None
        cs = ColourSource(reader, pattern, frame_pattern, demosaic_method)
        cs._close = reader.close
        return cs
    pattern, frame_pattern = source_cfa(source, cfa)
    if pattern is None:
        return None
    return ColourSource(source, pattern, frame_pattern, demosaic_method)


def rgb_to_luminance(rgb) -> np.ndarray:
    """Rec. 709 relative luminance of linear RGB (..., 3): float32 (...)
    (:data:`hybridhdr.camera.encoding.LUMINANCE_WEIGHTS`)."""
    a = np.asarray(rgb)
    if a.shape[-1:] != (3,):
        raise ValueError(f"RGB images must have a last axis of 3, got shape {a.shape}")
    return (a.astype(np.float64) @ np.asarray(LUMINANCE_WEIGHTS)).astype(np.float32)
