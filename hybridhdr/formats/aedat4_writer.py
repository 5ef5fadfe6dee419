"""iniVation AEDAT 4.0 writer (events, frames, triggers, IMU samples) through ``dv-processing``.

The file is written by ``dv_processing.io.MonoCameraWriter`` (the library iniVation's own tools
use), never by hand; install it with ``pip install 'hybridhdr[aedat4]'`` (``dv-processing``).
Read back with :class:`hybridhdr.formats.aedat4.Aedat4Reader` or dv-processing.

dv-processing terminates the whole process (C++ ``std::terminate``) when it is handed data out of
time order or a file name not ending in ``.aedat4``, so this writer checks everything first and
hands it only valid input:

* events arrive through :meth:`write_events` (checked for order, coordinates and polarity by
  :class:`~hybridhdr.formats.base.EventFileWriter`) and are spooled to a temporary file next to the output;
* frames, triggers and IMU samples are kept (they are small) and sorted by time;
* on :meth:`close` the streams are declared (events always; frames, triggers and IMU when there
  are any), then written interleaved in time order (events in packets of ``packet_events``), into
  ``.NAME.partial.aedat4``, renamed to the final name at the end. Nothing is left on error;
* dv-processing also terminates the process when the disk fills up under it, so before it starts
  the free space is checked against the file's largest possible size (uncompressed data plus
  overheads) and too little is an ``OSError`` ENOSPC. (Another program filling the disk while
  the file is written is not guarded against.)

Conversions (the inverse of the reader's, ``docs/conventions.md``):

* ``t`` -> event ``timestamp`` (µs) unchanged; ``p`` = +1 -> ``polarity`` true, -1 -> false;
* a frame -> ``dv::Frame`` with ``timestamp`` = ``t_start_us`` (start of exposure) and
  ``exposure`` = ``t_end_us - t_start_us``; RGB frames are stored BGR as OpenCV/dv expect; uint8
  and uint16 only (other dtypes are an error naming the conversion to make);
* a trigger ``(channel, edge)`` -> ``dv::TriggerType`` by the inverse of
  :data:`~hybridhdr.formats.aedat4.TRIGGER_TYPE_MAP` (channel 0 external signal, 1
  external generator, 2 APS frame, 3 APS exposure; +1 rising/start, -1 falling/end); other
  channels cannot be stored and are an error;
* an IMU sample (``IMU_DTYPE``) -> ``dv::IMU`` with the same timestamp and the float32 quantities
  in the fields of the same quantity and unit (:data:`hybridhdr.events.IMU_FIELDS`).

Options: ``compression`` (``"lz4"`` default, ``"lz4_high"``, ``"zstd"``, ``"zstd_high"``,
``"none"``), ``camera_name`` (default: the metadata's event-camera model, else ``"hybridhdr"``),
``packet_events`` (events per packet, default 100 000). Speed: about 0.4 million events per second
(dv-processing's Python API takes events one by one).
"""

from __future__ import annotations

import os

import numpy as np

from ..events import EVENT_DTYPE, IMU_FIELDS
from .base import EventFileWriter
from ..model import Frames

__all__ = ["Aedat4Writer", "TRIGGER_CODE", "COMPRESSION"]

#: (channel, edge) -> dv::TriggerType code; the inverse of aedat4.TRIGGER_TYPE_MAP without the
#: pulse (code 3, read as a rising edge of channel 0 and written back as one).
TRIGGER_CODE: dict[tuple[int, int], int] = {
    (0, 1): 1, (0, -1): 2,   # EXTERNAL_SIGNAL_RISING_EDGE / FALLING_EDGE
    (1, 1): 4, (1, -1): 5,   # EXTERNAL_GENERATOR_RISING_EDGE / FALLING_EDGE
    (2, 1): 6, (2, -1): 7,   # APS_FRAME_START / END
    (3, 1): 8, (3, -1): 9,   # APS_EXPOSURE_START / END
}

#: option value -> dv_processing.CompressionType name
COMPRESSION = {"none": "NONE", "lz4": "LZ4", "lz4_high": "LZ4_HIGH", "zstd": "ZSTD", "zstd_high": "ZSTD_HIGH"}


def _dv():
    try:
        import dv_processing as dv
    except ImportError as exc:
        raise ImportError("writing AEDAT4 needs dv-processing: pip install 'hybridhdr[aedat4]' "
                          "(or pip install dv-processing)") from exc
    return dv


class Aedat4Writer(EventFileWriter):
    """AEDAT 4.0 through dv-processing (see the module notes)."""

    format_name = "aedat4"
    supports = frozenset({"frames", "triggers", "imu"})

    def _partial_path(self):
        # dv-processing only writes names ending in '.aedat4' (others terminate the process)
        return self.path.with_name("." + self.path.name + ".partial.aedat4")

    def _open(self) -> None:
        dv = _dv()  # fail before anything is created when dv-processing is missing
        comp = str(self.options.get("compression", "lz4")).lower()
        if comp not in COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(COMPRESSION)}, got {comp!r}")
        self._compression = getattr(dv.CompressionType, COMPRESSION[comp])
        pe = self.options.get("packet_events", 100_000)
        if isinstance(pe, bool) or not isinstance(pe, (int, np.integer)) or pe < 1:
            raise ValueError(f"packet_events must be an integer >= 1, got {pe!r}")
        self._packet_events = int(pe)
        cam = self.metadata.event_camera
        self._camera_name = str(self.options.get("camera_name") or (cam.model if cam is not None and cam.model
                                                                    else "hybridhdr"))
        from .._util.atomic import claim_partial
        self._spool_path = self.path.with_name("." + self.path.name + ".events.partial")
        self._spool_fd = claim_partial(self._spool_path)  # exclusive, never through a symlink
        self._spool = os.fdopen(os.dup(self._spool_fd), "wb")
        self._frames: list[Frames] = []
        self._triggers: list[np.ndarray] = []
        self._imu: list[np.ndarray] = []

    def _write_events(self, events: np.ndarray) -> None:
        # file.write, not ndarray.tofile: a full disk is then OSError ENOSPC ("No space left on device")
        self._spool.write(memoryview(np.ascontiguousarray(events, dtype=EVENT_DTYPE)).cast("B"))

    def _write_triggers(self, triggers: np.ndarray) -> None:
        ch = triggers["channel"].astype(np.int64)
        edge = triggers["edge"].astype(np.int64)
        bad = [i for i, key in enumerate(zip(ch.tolist(), edge.tolist())) if key not in TRIGGER_CODE]
        if bad:
            i = bad[0]
            raise ValueError(f"{self.path}: trigger {i} (channel {int(ch[i])}, edge {int(edge[i])}) has no AEDAT4 "
                             f"trigger type; AEDAT4 stores channels 0-3 with edge +1/-1 (0 external signal, "
                             f"1 external generator, 2 APS frame, 3 APS exposure)")
        self._triggers.append(np.array(triggers, copy=True))

    def _write_imu(self, imu: np.ndarray) -> None:
        self._imu.append(np.array(imu, copy=True))

    def _write_frames(self, frames: Frames) -> None:
        imgs = np.asarray(frames.images)
        if imgs.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"{self.path}: AEDAT4 frames hold 8- or 16-bit codes, got {imgs.dtype}; convert them "
                             f"first (e.g. np.clip(img * 255, 0, 255).astype(np.uint8))")
        if imgs.ndim not in (3, 4) or (imgs.ndim == 4 and imgs.shape[3] != 3):
            raise ValueError(f"{self.path}: frames must be (K, H, W) or (K, H, W, 3), got {imgs.shape}")
        if self._frames:
            prev = np.asarray(self._frames[0].images)
            if prev.shape[1:] != imgs.shape[1:] or prev.dtype != imgs.dtype:
                raise ValueError(f"{self.path}: all frames of one AEDAT4 frame stream must have one shape and dtype; "
                                 f"got {prev.shape[1:]} {prev.dtype} then {imgs.shape[1:]} {imgs.dtype}")
        self._frames.append(frames)

    # -- finishing ------------------------------------------------------------------------------
    def _frame_list(self):
        """(t_start, exposure, BGR-or-grey image) of every frame, sorted by start time (stable)."""
        items = []
        for fr in self._frames:
            imgs = np.asarray(fr.images)
            for k in range(len(fr)):
                img = imgs[k]
                if img.ndim == 3:
                    img = img[..., ::-1]  # RGB -> BGR
                items.append((int(fr.t_start_us[k]), int(fr.t_end_us[k]) - int(fr.t_start_us[k]),
                              np.ascontiguousarray(img)))
        items.sort(key=lambda it: it[0])
        return items

    def _finish(self) -> None:
        dv = _dv()
        self._spool.close()
        trig = np.concatenate(self._triggers) if self._triggers else None
        if trig is not None:
            trig = trig[np.argsort(trig["t"], kind="stable")]
        imu = np.concatenate(self._imu) if self._imu else None
        if imu is not None:
            imu = imu[np.argsort(imu["t"], kind="stable")]
        n_imu = 0 if imu is None else len(imu)
        frames = self._frame_list()
        ss = self.sensor_size
        cfg = dv.io.MonoCameraWriter.Config(self._camera_name)
        cfg.addEventStream((ss.width, ss.height))
        if frames:
            h, w = frames[0][2].shape[:2]
            cfg.addFrameStream((w, h))
        if trig is not None and len(trig):
            cfg.addTriggerStream()
        if n_imu:
            cfg.addImuStream()
        cfg.compression = self._compression
        self._check_free_space(frames, 0 if trig is None else len(trig), n_imu)
        writer = dv.io.MonoCameraWriter(str(self.tmp_path), cfg)
        try:
            fi = ti = ii = 0
            n_trig = 0 if trig is None else len(trig)
            # dv.IMU's argument order: timestamp, temperature, accelerometer x/y/z, gyroscope x/y/z,
            # magnetometer x/y/z
            imu_order = [name for dv_name in ("temperature", "accelerometerX", "accelerometerY", "accelerometerZ",
                                              "gyroscopeX", "gyroscopeY", "gyroscopeZ", "magnetometerX",
                                              "magnetometerY", "magnetometerZ")
                         for name, _, d in IMU_FIELDS if d == dv_name]

            def flush_until(writer, t_max):
                nonlocal fi, ti, ii
                ib = ii
                while ii < n_imu and (t_max is None or int(imu["t"][ii]) <= t_max):
                    ii += 1
                if ii > ib:
                    cols = [imu["t"][ib:ii].tolist()] + [imu[name][ib:ii].tolist() for name in imu_order]
                    writer.writeImuPacket(dv.IMUPacket(dv.IMUPacket.ImuVector([dv.IMU(*v) for v in zip(*cols)])))
                # frames and triggers up to t_max, in time order, before the events after them
                tb = ti
                while ti < n_trig and (t_max is None or int(trig["t"][ti]) <= t_max):
                    ti += 1
                if ti > tb:
                    vec = dv.TriggerPacket.TriggersVector(
                        [dv.Trigger(int(t), dv.TriggerType(TRIGGER_CODE[(int(c), int(e))]))
                         for t, c, e in zip(trig["t"][tb:ti].tolist(), trig["channel"][tb:ti].tolist(),
                                            trig["edge"][tb:ti].tolist())])
                    writer.writeTriggerPacket(dv.TriggerPacket(vec))
                while fi < len(frames) and (t_max is None or frames[fi][0] <= t_max):
                    t0, exp, img = frames[fi]
                    writer.writeFrame(dv.Frame(t0, exp, 0, 0, img, dv.FrameSource.SENSOR))
                    fi += 1

            n_total = self.n_events
            step = self._packet_events
            with open(self._spool_path, "rb") as f:
                for start in range(0, n_total, step):
                    ev = np.fromfile(f, dtype=EVENT_DTYPE, count=min(step, n_total - start))
                    if len(ev) == 0:
                        break
                    flush_until(writer, int(ev["t"][0]))
                    store = dv.EventStore()
                    push = store.push_back
                    for t, x, y, p in zip(ev["t"].tolist(), ev["x"].tolist(), ev["y"].tolist(),
                                          (ev["p"] > 0).tolist()):
                        push(t, x, y, p)
                    writer.writeEvents(store)
            flush_until(writer, None)
        finally:
            del writer  # dv-processing finishes the file (and its data table) when the writer is destroyed
            import gc
            gc.collect()
        self._remove_spool()

    def _size_bound(self, frames, n_triggers: int, n_imu: int = 0) -> int:
        """Bytes the file can take at most: everything uncompressed (LZ4/ZSTD expand incompressible
        data by < 1 %) plus the per-packet, per-frame and header overheads (an IMU sample is a
        FlatBuffer table of 11 fields, at most 96 bytes: 52 of fields and offset to its vtable, up to 8
        of padding, a 26-byte vtable and the vector's 4-byte offset to it)."""
        n_packets = (-(-self.n_events // self._packet_events) + len(frames) + max(1, n_triggers)
                     + max(1, n_imu))
        frame_bytes = sum(int(img.nbytes) for _, _, img in frames)
        return (int(1.01 * (16 * self.n_events + frame_bytes + 32 * n_triggers + 96 * n_imu)) + 256 * n_packets
                + (64 << 10))

    def _check_free_space(self, frames, n_triggers: int, n_imu: int = 0) -> None:
        """Refuse (ENOSPC) before dv-processing starts when the disk cannot hold the file: on a full
        disk dv-processing's writer thread terminates the whole process instead of raising."""
        import errno
        import shutil
        need = self._size_bound(frames, n_triggers, n_imu)
        free = shutil.disk_usage(self.tmp_path.parent).free
        if free < need:
            raise OSError(errno.ENOSPC, f"No space left on device: {self.path} may need up to {need:,} bytes "
                                        f"(the uncompressed size; dv-processing would stop the process on a full "
                                        f"disk), {free:,} bytes free; nothing was written")

    def _remove_spool(self) -> None:
        try:
            if not self._spool.closed:
                self._spool.close()
        except Exception:
            pass
        try:
            os.unlink(self._spool_path)
        except FileNotFoundError:
            pass
        from .._util.atomic import release_partial
        release_partial(getattr(self, "_spool_fd", None))
        self._spool_fd = None

    def _cleanup(self) -> None:
        if hasattr(self, "_spool"):
            self._remove_spool()
