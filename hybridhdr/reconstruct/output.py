"""Writing a reconstruction as it is produced: :class:`VideoWriter` streams frames to a folder.

Memory is bounded by ``queue_frames`` frames, independent of the video's length: EXR files are
encoded by a bounded pool of writer processes (the OpenEXR binding holds the GIL while it
compresses, so threads would stall the filter), ``timestamps.txt`` is written line by line, and
the previews are tone-mapped from a spill file once the whole video is known (their limits are
percentiles over the whole video, computed exactly by
:class:`~hybridhdr.formats.images.LogPercentiles`). ``writers=0`` is the serial path (everything in
the calling thread); the pool writes the same bytes. The command line writes into
:class:`~hybridhdr._util.atomic.AtomicFolder` (``OUT.partial/`` → ``OUT``); :data:`OUTPUTS` names
the files a run writes. The file formats (EXR, PNG, MP4, tone mapping) are
:mod:`hybridhdr.formats.images`.
"""

from __future__ import annotations

import errno
import math
import os
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .._util.atomic import current_umask
from ..formats.images import (DEFAULT_EXR_COMPRESSION, TIMESTAMPS_HEADER, LogPercentiles, check_frame, check_tone,
                              exr_compression, MP4Stream, write_png, apply_display_map, display_map_centred, display_map_from,
                              write_exr)

__all__ = ["VideoWriter", "write_video", "OUTPUTS"]

#: The files a reconstruct run writes into its output folder (the only ones ``--overwrite`` replaces).
OUTPUTS = ("frame_*.exr", "timestamps.txt", "run.json", "preview.mp4", "previews/preview_*.png")


# -- the streaming writer --------------------------------------------------------------------------

def _task_exr(path, img, compression, channel):
    write_exr(path, img, compression=compression, channel=channel)
    return 1


def _task_png(spill, shape, index, path, display):
    fr = _read_spill(spill, shape, index)
    write_png(path, apply_display_map(fr, display))
    return 1


def _read_spill(spill, shape, index) -> np.ndarray:
    n = int(np.prod(shape))
    with open(spill, "rb") as f:
        f.seek(int(index) * n * 4)
        b = f.read(n * 4)
    if len(b) != n * 4:
        raise OSError(errno.EIO, f"{spill}: short read of frame {index}")
    return np.frombuffer(b, np.float32).reshape(shape)


def _worker_init(umask: int | None = None):
    import signal
    from .._util.procs import die_with_parent
    die_with_parent()  # a kill -9 of the command ends its writers too (no orphans blocked on a pipe)
    if umask is not None:  # a forkserver child inherits the server's umask, not this run's
        os.umask(umask)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and shuts the pool down
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_DFL)


def _make_pool(n: int, backend: str):
    """(executor, kind): processes (fork when this process runs one thread, else forkserver), or threads."""
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
    if backend == "thread":
        return ThreadPoolExecutor(n, thread_name_prefix="hybridhdr-writer"), "thread"
    import multiprocessing as mp
    methods = mp.get_all_start_methods()
    if "fork" in methods and threading.active_count() == 1 and sys.platform.startswith("linux"):
        ctx, kind = mp.get_context("fork"), "process (fork)"
    elif "forkserver" in methods:
        ctx, kind = mp.get_context("forkserver"), "process (forkserver)"
        ctx.set_forkserver_preload(["hybridhdr.reconstruct.output"])
    else:  # pragma: no cover - spawn platforms
        ctx, kind = mp.get_context("spawn"), "process (spawn)"
    ex = ProcessPoolExecutor(n, mp_context=ctx, initializer=_worker_init, initargs=(current_umask(),))
    # start every worker now, while this process may still be single-threaded (3.11 forks them all
    # at the first submit): later forks would copy a process whose other threads hold locks
    for f in [ex.submit(int, 0) for _ in range(n)]:
        f.result()
    return ex, kind


class VideoWriter:
    """Stream reconstructed frames into ``out_dir`` (an existing, preferably empty folder).

    ``write(t_us, frame)`` for each frame in time order, then ``close()`` (returns what was
    written) or ``abort()``; also a context manager (aborts on an exception). Files:
    ``frame_NNNNNN.exr`` (if ``exr``), ``timestamps.txt`` (``t_us filename`` per frame, every
    frame even without EXR), ``previews/preview_NNNNNN.png`` (``png``), ``preview.mp4``
    (``mp4``, every frame, playing at ``playback_fps``).

    Parameters
    ----------
    writers : int or None
        Writer processes (or threads, ``backend="thread"``); 0 writes everything in the calling
        thread (the serial path, same bytes). None: ``min(2, os.cpu_count())``.
    queue_frames : int or None
        Frames waiting for a writer at most (``write`` blocks beyond that); default
        ``2 * writers + 2``. Memory stays bounded by it whatever the video's length.
    on_written : callable(int), optional
        Called with the number of images written (EXR files, PNG files, MP4 frames) as they
        complete, from any thread.
    low_percentile, high_percentile, gamma
        Preview tone mapping (:func:`tone_map`) of an HDR video. A video that is not HDR (99.5th
        percentile at most the clip level 1.0, or within :data:`~hybridhdr.formats.images.LOG_MAP_RATIO`
        of the 5th) is shown linearly instead, up to max(1, 99.5th percentile), with
        ``display_gamma`` (2.2: linear light on a display), as ``hybridhdr view`` shows it
        (:func:`hybridhdr.formats.images.display_map_from`); the log map had lifted a low-range
        scene's dark tail to mid grey.

    With previews, the frames are also appended to a spill file in ``out_dir``
    (``.preview-spill.f32``, 4 bytes per value, removed by ``close``/``abort``): the previews'
    tone-mapping limits are percentiles over the whole video, so they are made after the last
    frame, by the pool (PNG) and an ffmpeg process (MP4) in parallel.
    """

    SPILL_NAME = ".preview-spill.f32"

    def __init__(self, out_dir, *, exr: bool = True, compression: str = DEFAULT_EXR_COMPRESSION,
                 png: bool = False, mp4: bool = False, playback_fps: float = 30.0, writers: int | None = None,
                 backend: str = "process", queue_frames: int | None = None, on_written=None,
                 prefix: str = "frame_", channel: str = "Y", low_percentile: float = 1.0,
                 high_percentile: float = 99.0, gamma: float = 1.0, display_gamma: float = 2.2):
        self.out = Path(out_dir)
        if not self.out.is_dir():
            raise FileNotFoundError(f"output folder {self.out} does not exist")
        if exr:
            exr_compression(compression)
        if mp4 and not playback_fps > 0:
            raise ValueError(f"playback_fps must be > 0, got {playback_fps}")
        check_tone(low_percentile, high_percentile, gamma)
        if backend not in ("process", "thread"):
            raise ValueError(f"backend must be 'process' or 'thread', got {backend!r}")
        if writers is None:
            writers = min(2, os.cpu_count() or 1)
        if isinstance(writers, bool) or not isinstance(writers, (int, np.integer)) or writers < 0:
            raise ValueError(f"writers must be an int >= 0, got {writers!r}")
        self.exr, self.compression, self.png, self.mp4 = bool(exr), str(compression).lower(), bool(png), bool(mp4)
        self.playback_fps = float(playback_fps)
        self.prefix, self.channel = prefix, channel
        if not (math.isfinite(display_gamma) and display_gamma > 0):
            raise ValueError(f"display_gamma must be > 0, got {display_gamma}")
        self.tone = dict(low_percentile=low_percentile, high_percentile=high_percentile, gamma=gamma,
                         display_gamma=display_gamma)
        self.events_only = False  # set_display
        self.n_writers = int(writers)
        self.queue_frames = int(queue_frames) if queue_frames else 2 * self.n_writers + 2
        self.on_written = on_written
        self.n = 0
        self.shape = None
        self.t_first = self.t_last = None
        self.error: BaseException | None = None
        self._closed = False
        self._pending = set()
        self._lock = threading.Lock()
        self._slots = threading.BoundedSemaphore(self.queue_frames)
        self._pool, self.backend = (None, "serial")
        self._spill_path = self.out / self.SPILL_NAME
        self._spill = None
        self._spill_q = None
        self._spill_thread = None
        self._hist = LogPercentiles() if (png or mp4) else None
        self.timings = {}
        self._t0 = time.perf_counter()
        self._ts = open(self.out / "timestamps.txt", "w", encoding="utf-8")
        try:
            self._ts.write(TIMESTAMPS_HEADER)
            if self._hist is not None:
                self._spill = open(self._spill_path, "wb")
            if self.n_writers > 0:
                self._pool, self.backend = _make_pool(self.n_writers, backend)
                if self._hist is not None:
                    self._spill_q = queue.Queue(maxsize=4)
                    self._spill_thread = threading.Thread(target=self._spill_loop, name="hybridhdr-spill",
                                                          daemon=True)
                    self._spill_thread.start()
        except BaseException:
            self.abort()
            raise

    # -- producer side
    def __enter__(self):
        return self

    def __exit__(self, et, ev, tb):
        if et is not None:
            self.abort()
        elif not self._closed:
            self.close()

    def _written(self, k: int = 1) -> None:
        if self.on_written is not None:
            self.on_written(k)

    def _raise_pending_error(self) -> None:
        if self.error is not None:
            raise self.error

    def _done(self, fut) -> None:
        with self._lock:
            self._pending.discard(fut)
        self._slots.release()
        if fut.cancelled():
            return
        e = fut.exception()
        if e is not None:
            if self.error is None:
                self.error = e
        else:
            self._written(1)

    def _submit(self, fn, *args) -> None:
        while not self._slots.acquire(timeout=0.2):
            self._raise_pending_error()
        self._raise_pending_error()
        try:
            fut = self._pool.submit(fn, *args)
        except BaseException:
            self._slots.release()
            raise
        with self._lock:
            self._pending.add(fut)
        fut.add_done_callback(self._done)

    def write(self, t_us: int, frame) -> None:
        """Queue one frame (blocks while ``queue_frames`` frames wait); raises a writer's error."""
        if self._closed:
            raise ValueError("write() on a closed VideoWriter")
        self._raise_pending_error()
        a = check_frame(frame)
        if self.shape is None:
            self.shape = a.shape
        elif a.shape != self.shape:
            raise ValueError(f"frame {self.n} has shape {a.shape}, the first had {self.shape}")
        t = int(t_us)
        if self.t_last is not None and t <= self.t_last:
            raise ValueError(f"frame times must increase: {t} after {self.t_last}")
        name = f"{self.prefix}{self.n:06d}.exr"
        self._ts.write(f"{t} {name}\n")
        if self.exr:
            if self._pool is None:
                write_exr(self.out / name, a, compression=self.compression, channel=self.channel)
                self._written(1)
            else:
                self._submit(_task_exr, str(self.out / name), a, self.compression, self.channel)
        if self._hist is not None:
            if self._spill_q is None:
                self._spill_one(a)
            else:
                while True:
                    self._raise_pending_error()
                    try:
                        self._spill_q.put(a, timeout=0.2)
                        break
                    except queue.Full:
                        continue
        if self.t_first is None:
            self.t_first = t
        self.t_last = t
        self.n += 1

    def _spill_one(self, a) -> None:
        self._spill.write(a.tobytes())
        self._hist.add(a)

    def _spill_loop(self) -> None:
        while True:
            a = self._spill_q.get()
            if a is None:
                return
            if self.error is not None:
                continue  # drain
            try:
                self._spill_one(a)
            except BaseException as e:  # noqa: BLE001 - handed to the producer
                if self.error is None:
                    self.error = e

    def _spill_frames(self):
        for i in range(self.n):
            yield _read_spill(self._spill_path, self.shape, i)

    def _wait_pending(self) -> None:
        while True:
            with self._lock:
                fs = list(self._pending)
            if not fs:
                break
            for f in fs:
                try:
                    f.result()
                except BaseException:  # noqa: BLE001 - recorded by _done
                    pass
        self._raise_pending_error()

    def set_display(self, *, frame_encoding=None, events_only: bool = False) -> None:
        """Before :meth:`close`: the previews' display map as ``hybridhdr view`` makes it. The linear
        map's gamma follows the frames' encoding (:func:`~hybridhdr.formats.images.display_gamma`:
        2.2 for gamma/sRGB codes, else 1.0), so a preview looks like its frame; ``events_only``
        (a method without frames) gets the log map centred on mid grey
        (:func:`~hybridhdr.formats.images.display_map_centred`)."""
        from ..formats.images import display_gamma
        self.tone["display_gamma"] = display_gamma(frame_encoding)
        self.events_only = bool(events_only)

    def close(self) -> dict:
        """Finish every file; returns ``{"exr": n, "exr_compression", "png": n, "mp4": name, ...}``."""
        if self._closed:
            raise ValueError("VideoWriter already closed")
        try:
            res = self._close()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return res

    def _close(self) -> dict:
        if self._spill_thread is not None:
            self._spill_q.put(None)
            self._spill_thread.join()
            self._spill_thread = None
        if self._pool is not None:
            self._wait_pending()
        self._raise_pending_error()
        self._ts.close()
        self.timings["frames_s"] = time.perf_counter() - self._t0
        written = {"frames": self.n, "backend": self.backend, "writers": self.n_writers}
        if self.exr:
            written["exr"] = self.n
            written["exr_compression"] = self.compression
        if self._hist is not None:
            self._spill.close()
            self._spill = None
            if self.n:
                written.update(self._previews())
            os.unlink(self._spill_path)
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        self.timings["total_s"] = time.perf_counter() - self._t0
        return written

    def _previews(self) -> dict:
        t0 = time.perf_counter()
        lo, hi, p5, p995, mid = self._hist.percentiles(self._spill_frames, (self.tone["low_percentile"],
                                                                           self.tone["high_percentile"], 5.0, 99.5,
                                                                           50.0))
        if hi <= lo:
            hi = lo + 1e-6
        if self.events_only:  # no absolute scale: log map centred on mid grey
            disp = display_map_centred(lo, mid, hi)
        else:  # log map for an HDR video, linear (display gamma) otherwise: formats.images.display_map_from
            disp = display_map_from(math.exp(p5), math.exp(p995), (lo, hi), gamma=self.tone["display_gamma"],
                                    log_gamma=self.tone["gamma"])
        out = {"preview_log_limits": [lo, hi], "preview_display": dict(disp)}
        mp4_thread = None
        mp4_err = []
        if self.mp4:
            def encode():
                try:
                    s = MP4Stream(self.out / "preview.mp4", self.shape, self.playback_fps)
                    try:
                        for i, fr in enumerate(self._spill_frames()):
                            if mp4_err:
                                break
                            s.write(apply_display_map(fr, disp))
                            self._written(1)
                    finally:
                        s.close()
                except BaseException as e:  # noqa: BLE001 - re-raised below
                    mp4_err.append(e)
            if self._pool is None:
                encode()
            else:
                mp4_thread = threading.Thread(target=encode, name="hybridhdr-mp4", daemon=True)
                mp4_thread.start()
        try:
            if self.png:
                d = self.out / "previews"
                d.mkdir(exist_ok=True)
                for i in range(self.n):
                    p = str(d / f"preview_{i:06d}.png")
                    if self._pool is None:
                        _task_png(str(self._spill_path), self.shape, i, p, disp)
                        self._written(1)
                    else:
                        self._submit(_task_png, str(self._spill_path), self.shape, i, p, disp)
                    if mp4_err:
                        break
                if self._pool is not None:
                    self._wait_pending()
                out["png"] = self.n
        finally:
            if mp4_thread is not None:
                if self.error is not None:
                    mp4_err.append(self.error)
                mp4_thread.join()
        if mp4_err:
            raise mp4_err[0]
        if self.mp4:
            out["mp4"] = "preview.mp4"
            out["mp4_playback_fps"] = self.playback_fps
        self.timings["previews_s"] = time.perf_counter() - t0
        return out

    def abort(self) -> None:
        """Stop: cancel queued work, end the pool, close and remove the spill file. Written files stay
        (the caller removes its folder)."""
        self._closed = True
        if self._spill_thread is not None:
            if self.error is None:
                self.error = RuntimeError("aborted")
            try:
                while True:
                    self._spill_q.get_nowait()
            except queue.Empty:
                pass
            self._spill_q.put(None)
            self._spill_thread.join()
            self._spill_thread = None
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        for f in (self._spill, self._ts):
            if f is not None:
                try:
                    f.close()
                except OSError:
                    pass
        self._spill = None
        try:
            os.unlink(self._spill_path)
        except FileNotFoundError:
            pass


def write_video(video, out_dir, **kw) -> dict:
    """Write an in-memory Video with :class:`VideoWriter` (same files as the command line)."""
    with VideoWriter(out_dir, **kw) as w:
        for t, f in zip(video.t_us, video.frames):
            w.write(int(t), f)
        return w.close()
