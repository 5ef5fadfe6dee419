"""Resumable simulation: every render kept in a partial file beside the output.

A simulation's cost is its renders; everything after them (event sensor, frame camera, writer)
is fast and, for a given seed, deterministic. :class:`RenderCache` wraps a radiance source and
appends each render (time in µs and the float32 image, bit for bit) to ``OUT.resume`` (HDF5) as it
is made. An interrupted run (Ctrl-C, SIGTERM, an error) leaves that file; the next run with
``resume=True`` replays the whole pipeline from t = 0, taking every render it already has from the
file and rendering only the rest. The sampler chooses its times from the renders alone, so the
replay asks for the same times, gets the same images, draws the same random numbers, and writes
the same output as an uninterrupted run with the same seed. The renders do not depend on the
sensor, camera or sampling settings, only on the source, so the file records the source's
``describe()`` and a resume with another source is refused.

A partial is flushed to disk every ``flush_every`` renders (and on close); a process killed with
SIGKILL may lose the last few renders, or, if it died inside an HDF5 write, leave a file that
cannot be opened (then the run starts again: the message says so).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .._util.procs import raise_if_signalled

__all__ = ["RenderCache", "partial_path", "partial_source_info"]

#: the partial's format version (attrs["hybridhdr_render_cache"])
_VERSION = 1


def partial_path(out) -> Path:
    """The resumable partial of output ``out``: ``OUT.resume`` beside it."""
    out = Path(os.fspath(out))
    return out.with_name(out.name + ".resume")


def _key(describe: dict) -> str:
    return json.dumps(describe, sort_keys=True, default=str)


def partial_source_info(path) -> dict | None:
    """The ``describe()`` of the source a partial was rendered from (None when unreadable)."""
    import h5py
    try:
        with h5py.File(path, "r") as f:
            return json.loads(f.attrs["source"])
    except (OSError, KeyError, ValueError):
        return None


class RenderCache:
    """A radiance source whose renders are also stored in (and, on resume, read from) ``path``.

    Parameters
    ----------
    source : RadianceSource
    path : path of the partial (see :func:`partial_path`)
    resume : bool
        True: ``path`` must exist and hold renders of the same source (``describe()``); they are
        returned instead of rendering again. False: ``path`` must not exist.
    flush_every : int
        Renders between flushes to disk.

    Attributes
    ----------
    reused, rendered : int
        Renders taken from the partial, and made now.
    """

    def __init__(self, source, path, *, resume: bool = False, flush_every: int = 16):
        import h5py
        self._src = source
        self.path = Path(os.fspath(path))
        self.sensor_size = source.sensor_size
        self.duration_us = source.duration_us
        self.flush_every = max(1, int(flush_every))
        self.reused = self.rendered = 0
        self.calls = 0
        self._index: dict[int, int] = {}
        key = _key(source.describe())
        h, w = source.sensor_size.shape
        if resume:
            if not self.path.exists():
                raise ValueError(f"--resume: no partial {self.path} to resume (an interrupted run leaves one)")
            try:
                self._f = h5py.File(self.path, "r+")
            except OSError as e:
                raise ValueError(f"--resume: {self.path} cannot be read ({e}); the run that wrote it was killed "
                                 f"mid-write: delete it and run again without --resume") from None
            f = self._f
            if int(f.attrs.get("hybridhdr_render_cache", -1)) != _VERSION or "t_us" not in f or "images" not in f:
                f.close()
                raise ValueError(f"--resume: {self.path} is not a hybridhdr simulate partial (version {_VERSION})")
            if f.attrs["source"] != key:
                was = json.loads(f.attrs["source"])
                f.close()
                raise ValueError(f"--resume: {self.path} holds renders of another source or setting (it has "
                                 f"{was.get('scene', was.get('name', '?'))}; the scene, size, spp, variant or duration "
                                 f"differ); run with the same scene options, or --overwrite to start again")
            n = int(f.attrs.get("n", 0))  # rows written before the last flush
            if f["images"].shape[1:] != (h, w):
                f.close()
                raise ValueError(f"--resume: {self.path} has {f['images'].shape[1:]} images, expected {(h, w)}")
            ts = f["t_us"][:n]
            self._index = {int(t): i for i, t in enumerate(ts)}
            self._n = n
        else:
            if self.path.exists():
                raise ValueError(f"{self.path} exists (an interrupted run's partial): pass --resume to finish it, "
                                 f"or --overwrite to start again")
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = h5py.File(self.path, "w")
            f = self._f
            f.attrs["hybridhdr_render_cache"] = _VERSION
            f.attrs["source"] = key
            f.attrs["n"] = 0
            f.create_dataset("t_us", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
            f.create_dataset("images", shape=(0, h, w), maxshape=(None, h, w), dtype=np.float32, chunks=(1, h, w))
            self._n = 0

    def __getattr__(self, name):  # variant, spp, render_time_s, max_image_speed_px_per_s, describe ...
        return getattr(self._src, name)

    @property
    def renders(self) -> int:
        """Calls to :meth:`render` (stored ones included), so a resumed run counts as an uninterrupted one."""
        return self.calls

    def render(self, t_us: int) -> np.ndarray:
        raise_if_signalled()  # a signal whose exception Python dropped ends the run here
        t = int(t_us)
        self.calls += 1
        i = self._index.get(t)
        if i is not None:
            self.reused += 1
            return self._f["images"][i]
        img = np.asarray(self._src.render(t), np.float32)
        self.rendered += 1
        if self._f is not None:
            f = self._f
            n = self._n
            f["t_us"].resize((n + 1,))
            f["images"].resize((n + 1,) + img.shape)
            f["images"][n] = img
            f["t_us"][n] = t
            self._index[t] = n
            self._n = n + 1
            if self._n % self.flush_every == 0:
                f.attrs["n"] = self._n
                f.flush()
        return img

    def max_image_speed_px_per_s(self, t0_us, t1_us):
        return self._src.max_image_speed_px_per_s(t0_us, t1_us)

    def describe(self) -> dict:
        return self._src.describe()

    def close(self, *, keep: bool) -> None:
        """Close the partial; ``keep=False`` deletes it (the output is complete)."""
        f, self._f = self._f, None
        if f is not None:
            try:
                f.attrs["n"] = self._n
                f.close()
            except Exception:  # noqa: BLE001 - closing after an interrupted write: keep what is on disk
                pass
        if not keep:
            self.path.unlink(missing_ok=True)
