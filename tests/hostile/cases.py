"""Hostile-input suite: generated *semantic* cases for every reader, each run in a child process.

Each case builds a file that is well formed except for one hostile property (a bomb, a huge declared
size, non-finite values, a mistyped array, an overflowing timestamp, a header that disagrees with
the data) or a file that used to be falsely rejected. It is then read through the command line
(``hybridhdr info --json`` or ``capture recover``) in a child forked from a process that has
imported hybridhdr once (so a case costs milliseconds, not an interpreter start), with
``RLIMIT_AS`` = the address space at fork + ``--mem-gib`` GiB and a wall-clock timeout.

Outcome of a case (the table's columns):

* ``clean``: exit 1 with exactly one ``error:`` line and no traceback (cases expecting an error;
  ``usage`` cases: exit 2, an option refused by the parser; ``refused`` cases: exit 1 or 2), and
  the case's check (if any) holds;
* ``ok``: exit 0 and the expected result (cases that must be read, e.g. former false rejects);
* ``traceback``: an exception escaped (any traceback on stderr, or MemoryError under the cap);
* ``crash``: the child died from a signal (SIGSEGV, SIGABRT, SIGKILL by the OOM killer);
* ``hang``: it ran past the timeout and was killed;
* ``silent``: exit 0 where an error was expected, or a wrong result where success was expected.

Run ``python -m tests.hostile.cases [--quick] [--json]``; the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import resource
import signal
import struct
import sys
import tempfile
import time
import traceback
import zipfile
import zlib
from pathlib import Path

import numpy as np

COLUMNS = ("tried", "clean", "ok", "traceback", "crash", "hang", "silent")
CASES: list[tuple[str, str, object, str]] = []  # (reader, name, builder(dir) -> (argv, check), expect)


def case(reader: str, expect: str = "error"):
    def deco(fn):
        CASES.append((reader, fn.__name__, fn, expect))
        return fn
    return deco


# -- helpers ------------------------------------------------------------------------------------
def _events(n=1000, w=64, h=48, t0=0, span=1_000_000, seed=0):
    import hybridhdr as hh
    rng = np.random.default_rng(seed)
    return hh.make_events(np.sort(rng.integers(t0, t0 + span, n)), rng.integers(0, w, n), rng.integers(0, h, n),
                          rng.choice([-1, 1], n))


def _info(path, expect_events=None):
    argv = ["info", str(path), "--json"]
    if expect_events is None:
        return argv, None

    def check(stdout):
        info = json.loads(stdout.strip().splitlines()[-1])
        return info["events"] == expect_events, f"events {info['events']} != {expect_events}"
    return argv, check


def _container(path, n=100, frames=None, ss=(48, 64), **kw):
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    return write_recording(hh.Recording(_events(n, ss[1], ss[0]), ss, frames), path, **kw)


def _png_header_only(path, w, h):
    """A PNG whose IHDR declares w x h (8-bit grey) followed by a tiny IDAT: the size is in the header."""
    def chunk(typ, data):
        return struct.pack(">I", len(data)) + typ + data + struct.pack(">I", zlib.crc32(typ + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                           + chunk(b"IEND", b""))
    return path


def _ecd_folder(d, n_images=0, image=None, images_txt=None, events_txt=None):
    d.mkdir(parents=True, exist_ok=True)
    (d / "events.txt").write_text(events_txt if events_txt is not None else
                                  "".join(f"{i * 1e-3:.6f} {i % 10} {i % 7} {i % 2}\n" for i in range(50)))
    if images_txt is not None:
        (d / "images").mkdir(exist_ok=True)
        if image is not None:
            image(d / "images" / "a.png")
        (d / "images.txt").write_text(images_txt)
    return d


# -- hybridhdr container ------------------------------------------------------------------------
@case("hybridhdr")
def container_sensor_65536(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        f.attrs["sensor_height"] = f.attrs["sensor_width"] = 65536
    return _info(p)


@case("hybridhdr")
def container_declared_1e11_events_no_chunks(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        g = f["events"]
        for name, dt in (("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")):
            del g[name]
            g.create_dataset(name, shape=(10**11,), dtype=dt, chunks=(1 << 17,), compression="gzip")
    return _info(p)


@case("hybridhdr")
def container_nan_frames(d):
    import hybridhdr as hh
    import h5py
    p = _container(d / "r.h5", frames=hh.Frames(np.ones((2, 48, 64), np.float32), [0, 10], [5, 15]))
    with h5py.File(p, "a") as f:
        f["frames/images"][1] = np.nan
    return _info(p)


@case("hybridhdr")
def container_posinf_frames(d):
    import hybridhdr as hh
    import h5py
    p = _container(d / "r.h5", frames=hh.Frames(np.ones((2, 48, 64), np.float32), [0, 10], [5, 15]))
    with h5py.File(p, "a") as f:
        f["frames/images"][0, 3, 3] = np.inf
    return _info(p)


@case("hybridhdr")
def container_frames_10000sq_declared(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        g = f.create_group("frames")
        g.create_dataset("images", shape=(2, 10000, 10000), dtype="u1", chunks=(1, 10000, 10000))
        g["t_start_us"] = np.array([0, 10])
        g["t_end_us"] = np.array([5, 15])
    return _info(p)


@case("hybridhdr")
def container_frames_4gib_declared(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        g = f.create_group("frames")
        g.create_dataset("images", shape=(100, 8000, 8000), dtype="u1", chunks=(1, 8000, 8000))
        g["t_start_us"] = np.arange(100)
        g["t_end_us"] = np.arange(100)
    return _info(p)


@case("hybridhdr")
def container_v10_dense_index_forged(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        f.attrs["hybridhdr_format_version"] = "1.0"
        f["events"].create_dataset("ms_to_idx", shape=(10**12,), dtype="<i8", chunks=(1 << 16,))
    return _info(p)


@case("hybridhdr")
def container_events_t_float(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        t = f["events/t"][:]
        del f["events/t"]
        f["events/t"] = t.astype(np.float64)
    return _info(p)


@case("hybridhdr")
def container_index_inconsistent(d):
    import h5py
    p = _container(d / "r.h5", n=20000)
    with h5py.File(p, "a") as f:
        f["events/index_first"][-1] = 10**15
    return _info(p)


@case("hybridhdr", "ok")
def container_two_events_1_16_days_apart(d):
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    ev = hh.make_events([0, int(1.16 * 86400e6)], [0, 1], [0, 1], [1, -1])
    p = write_recording(hh.Recording(ev, (48, 64)), d / "r.h5")
    size = p.stat().st_size
    argv, check = _info(p, 2)
    return argv, lambda out: (check(out)[0] and size < 1 << 20, f"file {size} bytes")


@case("hybridhdr", "ok")
def container_int64_extreme_times(d):
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    big = np.iinfo(np.int64).max
    ev = hh.make_events([-big - 1, 0, big], [0, 1, 2], [0, 1, 2], [1, -1, 1])
    return _info(write_recording(hh.Recording(ev, (48, 64)), d / "r.h5"), 3)


# -- Prophesee ----------------------------------------------------------------------------------
def _dat(path, ev, header_extra=(), height=48, width=64):
    import hybridhdr as hh
    hh.write(hh.Recording(ev, (height, width)), path, "dat")
    data = Path(path).read_bytes()
    # replace the Height/Width lines
    lines = data.split(b"\n")
    out = [ln for ln in lines[:20] if not (ln.startswith(b"% Height") or ln.startswith(b"% Width"))]
    out = [ln for ln in out if ln.startswith(b"%")]
    rest = data[sum(len(ln) + 1 for ln in lines[:20] if ln.startswith(b"%")):]
    hdr = b"\n".join(out[:1] + [bytes(x, "ascii") for x in header_extra] + out[1:]) + b"\n"
    Path(path).write_bytes(hdr + rest)
    return path


@case("dat")
def dat_width_99999(d):
    return _info(_dat(d / "a.dat", _events(), ["% Height 48", "% Width 99999"]))


@case("dat")
def dat_height_smaller_than_data(d):
    return _info(_dat(d / "a.dat", _events(), ["% Height 10", "% Width 64"]))


@case("dat")
def dat_width_not_a_number(d):
    return _info(_dat(d / "a.dat", _events(), ["% Height 48", "% Width 1e9"]))


@case("evt3")
def evt3_format_height_100000(d):
    import hybridhdr as hh
    p = d / "a.raw"
    hh.write(hh.Recording(_events(), (48, 64)), p, "evt3")
    data = p.read_bytes()
    data = data.replace(b"height=48", b"height=100000", 1)
    p.write_bytes(data)
    return _info(p)


@case("evt2")
def evt2_geometry_zero(d):
    import hybridhdr as hh
    p = d / "a.raw"
    hh.write(hh.Recording(_events(), (48, 64)), p, "evt2")
    data = p.read_bytes()
    i = data.index(b"\n% end") if b"\n% end" in data else data.index(b"\n")
    data = data.replace(b"height=48", b"height=0", 1).replace(b"width=64", b"width=0", 1)
    if b"height=0" not in data:
        data = data[:i] + b"\n% geometry 0x0" + data[i:]
    p.write_bytes(data)
    return _info(p)


# -- AEDAT4 -------------------------------------------------------------------------------------
def _aedat4(path, size=(32, 24), compression="LZ4", n=200):
    import datetime  # noqa: F401
    import dv_processing as dv
    import hybridhdr as hh
    ev = _events(n, size[0], size[1])
    cfg = dv.io.MonoCameraWriter.Config("TestCam_ABC123")
    cfg.addEventStream(size)
    cfg.compression = getattr(dv.CompressionType, compression)
    w = dv.io.MonoCameraWriter(str(path), cfg)
    store = dv.EventStore()
    for t, x, y, p in ev.tolist():
        store.push_back(int(t), int(x), int(y), bool(p > 0))
    w.writeEvents(store)
    del w
    return path, hh


def _aedat4_with_packet(path, payload: bytes, compression="LZ4"):
    """A dv-written header (data table position set to -1) followed by one event packet ``payload``."""
    from hybridhdr.formats import aedat4 as A
    _aedat4(path, compression=compression)
    data = Path(path).read_bytes()
    hsize = struct.unpack_from("<i", data, len(A.MAGIC))[0]
    start = len(A.MAGIC) + 4 + hsize
    header = bytearray(data[:start])
    # the table position is an int64 in the header equal to some offset >= start: set it to -1
    for off in range(len(A.MAGIC) + 4, start - 7):
        v = struct.unpack_from("<q", header, off)[0]
        if start <= v <= len(data) and v > start:
            struct.pack_into("<q", header, off, -1)
            break
    Path(path).write_bytes(bytes(header) + struct.pack("<ii", 0, len(payload)) + payload)
    return path


@case("aedat4")
def aedat4_resolution_10000sq(d):
    p, _ = _aedat4(d / "a.aedat4", size=(10000, 10000), n=10)
    return _info(p)


@case("aedat4")
def aedat4_lz4_packet_bomb_300mib(d):
    import lz4.frame
    return _info(_aedat4_with_packet(d / "a.aedat4", lz4.frame.compress(b"\0" * (300 << 20)), "LZ4"))


@case("aedat4")
def aedat4_zstd_packet_bomb_300mib(d):
    import zstandard
    return _info(_aedat4_with_packet(d / "a.aedat4", zstandard.ZstdCompressor().compress(b"\0" * (300 << 20)),
                                     "ZSTD"))


@case("aedat4")
def aedat4_zstd_declares_1tib(d):
    # frame header: single segment, 8-byte content size = 2^40, then one RLE block of zeros
    frame = b"\x28\xb5\x2f\xfd\xe0" + struct.pack("<Q", 1 << 40) + struct.pack("<I", (1 << 3 | 1 << 1 | 1) | (1 << 23))[:3] + b"\0"
    return _info(_aedat4_with_packet(d / "a.aedat4", frame, "ZSTD"))


# -- ECD ----------------------------------------------------------------------------------------
@case("ecd")
def ecd_image_time_1e300(d):
    f = _ecd_folder(d / "ecd", images_txt="1e300 images/a.png\n",
                    image=lambda p: _png_header_only(p, 64, 48))
    return _info(f)


@case("ecd")
def ecd_60_refs_to_9500sq_png(d):
    f = _ecd_folder(d / "ecd", images_txt="".join(f"{i * 0.01:.2f} images/a.png\n" for i in range(60)),
                    image=lambda p: _png_header_only(p, 9500, 9500))
    return _info(f)


@case("ecd")
def ecd_200_refs_to_6000sq_png(d):
    f = _ecd_folder(d / "ecd", images_txt="".join(f"{i * 0.01:.2f} images/a.png\n" for i in range(200)),
                    image=lambda p: _png_header_only(p, 6000, 6000))
    return ["info", str(f), "--json", "--from", "ecd"], None


@case("ecd")
def ecd_png_bomb_100k_sq(d):
    f = _ecd_folder(d / "ecd", images_txt="0.0 images/a.png\n", image=lambda p: _png_header_only(p, 100000, 100000))
    return _info(f)


@case("ecd")
def ecd_events_nan_time(d):
    return _info(_ecd_folder(d / "ecd", events_txt="0.1 1 1 1\nnan 2 2 0\n"))


@case("ecd")
def ecd_events_time_1e300(d):
    return _info(_ecd_folder(d / "ecd", events_txt="0.1 1 1 1\n1e300 2 2 0\n"))


@case("ecd")
def ecd_events_inf_time(d):
    return _info(_ecd_folder(d / "ecd", events_txt="0.1 1 1 1\ninf 2 2 0\n"))


@case("ecd")
def ecd_coordinates_imply_65536_sensor(d):
    return _info(_ecd_folder(d / "ecd", events_txt="0.1 1 1 1\n0.2 65535 65535 0\n"))


# -- E2VID --------------------------------------------------------------------------------------
_E2VID_BODY = "".join(f"{i * 1e-3:.6f} {i % 10} {i % 7} {i % 2}\n" for i in range(30))


@case("e2vid")
def e2vid_header_99999(d):
    p = d / "e.txt"
    p.write_text("99999 10\n" + _E2VID_BODY)
    return _info(p)


@case("e2vid", "ok")
def e2vid_utf8_bom(d):
    p = d / "e.txt"
    p.write_bytes(b"\xef\xbb\xbf" + ("64 48\n" + _E2VID_BODY).encode())
    return _info(p, 30)


@case("e2vid", "ok")
def e2vid_header_only(d):
    p = d / "e.txt"
    p.write_text("64 48\n")
    return _info(p, 0)


@case("e2vid", "ok")
def e2vid_5kb_of_comments(d):
    p = d / "e.txt"
    p.write_text("64 48\n" + "# comment line that is fairly long to fill the head\n" * 100 + _E2VID_BODY)
    return _info(p, 30)


def _zip(path, text: str):
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("events.txt", text)
    return path


@case("e2vid")
def e2vid_zip_corrupt_deflate(d):
    p = _zip(d / "e.zip", "64 48\n" + _E2VID_BODY * 50)
    data = bytearray(p.read_bytes())
    off = 30 + len("events.txt")
    for i in range(off + 20, off + 60):
        data[i] ^= 0x5A
    p.write_bytes(bytes(data))
    return ["info", str(p), "--json", "--from", "e2vid"], None


@case("e2vid")
def e2vid_zip_encrypted_member(d):
    p = _zip(d / "e.zip", "64 48\n" + _E2VID_BODY)
    data = bytearray(p.read_bytes())
    data[6] |= 1  # local header: encrypted
    cd = data.rfind(b"PK\x01\x02")
    data[cd + 8] |= 1  # central directory: encrypted
    p.write_bytes(bytes(data))
    return ["info", str(p), "--json", "--from", "e2vid"], None


# -- DSEC / Monash ------------------------------------------------------------------------------
@case("dsec")
def dsec_declares_1e11_events_no_chunks(d):
    import h5py
    p = d / "events.h5"
    with h5py.File(p, "w") as f:
        g = f.create_group("events")
        for name, dt in (("x", "<u2"), ("y", "<u2"), ("t", "<u4"), ("p", "u1")):
            g.create_dataset(name, shape=(10**11,), dtype=dt, chunks=(1 << 16,), compression="gzip")
        f["ms_to_idx"] = np.zeros(4, np.uint64)
        f["t_offset"] = np.int64(0)
    return _info(p)


@case("dsec")
def dsec_height_attr_100000(d):
    import h5py
    p = d / "events.h5"
    with h5py.File(p, "w") as f:
        g = f.create_group("events")
        for name in "xytp":
            g[name] = np.zeros(10, np.uint16 if name in "xy" else np.uint32 if name == "t" else np.uint8)
        f["t_offset"] = np.int64(0)
        f.attrs["height"], f.attrs["width"] = 100000, 640
    return _info(p)


def _monash(path, images=None, attrs=None):
    import h5py
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g["xs"] = np.arange(10, dtype=np.int16)
        g["ys"] = np.arange(10, dtype=np.int16)
        g["ts"] = np.linspace(0, 1, 10)
        g["ps"] = np.ones(10, bool)
        f.attrs["sensor_resolution"] = (48, 64)
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        if images is not None:
            images(f.create_group("images"))
    return path


@case("monash")
def monash_nan_float_image(d):
    def im(g):
        a = np.ones((48, 64), np.float32)
        a[1, 1] = np.nan
        g["image000000000"] = a
        g["image000000000"].attrs["timestamp"] = 0.5
    return _info(_monash(d / "m.h5", im))


@case("monash")
def monash_image_10000sq_declared(d):
    def im(g):
        g.create_dataset("image000000000", shape=(10000, 10000), dtype="u1", chunks=(1000, 1000))
        g["image000000000"].attrs["timestamp"] = 0.5
    return _info(_monash(d / "m.h5", im, {"sensor_resolution": (48, 64)}))


@case("monash")
def monash_image_timestamp_1e300(d):
    def im(g):
        g["image000000000"] = np.zeros((48, 64), np.uint8)
        g["image000000000"].attrs["timestamp"] = 1e300
    return _info(_monash(d / "m.h5", im))


# -- AKF .mat -----------------------------------------------------------------------------------
def _mat5(path, events):
    import scipy.io
    scipy.io.savemat(path, {"events": events, "im_height": 48.0, "im_width": 64.0})
    return path


@case("akf_mat")
def mat5_events_cell(d):
    return _info(_mat5(d / "a.mat", np.array([[1.0, 2.0], [3.0, 4.0]], dtype=object)))


@case("akf_mat")
def mat5_events_struct(d):
    return _info(_mat5(d / "a.mat", {"t": np.arange(4.0)}))


@case("akf_mat")
def mat5_events_sparse(d):
    import scipy.sparse
    return _info(_mat5(d / "a.mat", scipy.sparse.csc_matrix(np.ones((3, 4)))))


@case("akf_mat")
def mat5_events_char(d):
    return _info(_mat5(d / "a.mat", "1 2 3 4"))


def _mat73(path, events=None, image=None, extra=None):
    from hybridhdr.formats.akf_mat import matlab_v73_header
    import h5py
    with h5py.File(path, "w", userblock_size=512) as f:
        if events is not None:
            ds = f.create_dataset("events", data=events)
            ds.attrs["MATLAB_class"] = np.bytes_(b"double" if events.dtype.kind == "f" else b"char")
        for k, v in (extra or {}).items():
            ds = f.create_dataset(k, data=np.asarray(v, np.float64).reshape(1, 1))
            ds.attrs["MATLAB_class"] = np.bytes_(b"double")
        if image is not None:
            ds = f.create_dataset("image", data=image)
            ds.attrs["MATLAB_class"] = np.bytes_(b"double")
            ds = f.create_dataset("time_image", data=np.arange(image.shape[0], dtype=np.float64).reshape(-1, 1))
            ds.attrs["MATLAB_class"] = np.bytes_(b"double")
    with open(path, "r+b") as fh:
        fh.write(matlab_v73_header())
    return path


@case("akf_mat")
def mat73_events_char(d):
    return _info(_mat73(d / "a.mat", np.frombuffer(b"1 2 3 4 5 6 7 8", np.uint8).astype(np.uint16).reshape(1, -1)
                        [:, :12].reshape(4, 3), extra={"im_height": 48, "im_width": 64}))


@case("akf_mat")
def mat73_nan_image(d):
    im = np.ones((2, 64, 48))
    im[1, 2, 3] = np.nan
    ev = np.array([[1.0, 2.0], [1, 1], [1, 1], [1, 0]])  # MATLAB N x 4 stored transposed
    return _info(_mat73(d / "a.mat", ev, im, {"im_height": 48, "im_width": 64}))


@case("akf_mat")
def mat73_im_height_100000(d):
    ev = np.array([[1.0, 2.0], [1, 1], [1, 1], [1, 0]])
    return _info(_mat73(d / "a.mat", ev, None, {"im_height": 100000, "im_width": 64}))


@case("akf_mat")
def mat73_events_inf_time(d):
    ev = np.array([[1.0, np.inf], [1, 1], [1, 1], [1, 0]])
    return _info(_mat73(d / "a.mat", ev, None, {"im_height": 48, "im_width": 64}))


# -- rosbag -------------------------------------------------------------------------------------
def _ros1_bag(path):
    from rosbags.rosbag1 import Writer
    from hybridhdr.formats import rosbag as R
    ts = R.make_typestore(ros2=False)
    Event, EA = ts.types["dvs_msgs/msg/Event"], ts.types[R.EVENT_ARRAY]
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    evs = [Event(x=i % 10, y=i % 7, ts=Time(sec=1, nanosec=i * 1000), polarity=bool(i % 2)) for i in range(20)]
    msg = EA(header=Header(seq=0, stamp=Time(sec=1, nanosec=0), frame_id="cam"), height=48, width=64, events=evs)
    tmp = path.with_name("tmp.bag")
    with Writer(tmp) as w:
        c = w.add_connection("/dvs/events", R.EVENT_ARRAY, typestore=ts)
        w.write(c, 1_000_000_000, ts.serialize_ros1(msg, R.EVENT_ARRAY))
    tmp.rename(path)
    return path


def _ros1_chunk_size(path, new_size: int, compression: str = "bz2"):
    """A compressed ROS 1 bag whose (first) chunk header declares ``new_size`` decompressed bytes."""
    from rosbags.rosbag1 import Writer
    from hybridhdr.formats import rosbag as R
    ts = R.make_typestore(ros2=False)
    Event, EA = ts.types["dvs_msgs/msg/Event"], ts.types[R.EVENT_ARRAY]
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    evs = [Event(x=i % 10, y=i % 7, ts=Time(sec=1, nanosec=i), polarity=True) for i in range(200_000)]
    msg = EA(header=Header(seq=0, stamp=Time(sec=1, nanosec=0), frame_id="cam"), height=48, width=64, events=evs)
    w = Writer(path)
    w.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
    with w:
        c = w.add_connection("/dvs/events", R.EVENT_ARRAY, typestore=ts)
        w.write(c, 1_000_000_000, ts.serialize_ros1(msg, R.EVENT_ARRAY))
    b = bytearray(path.read_bytes())
    i = b.index(b"size=", b.index(b"op=\x05") - 64)  # the chunk header's size field
    struct.pack_into("<I", b, i + 5, new_size)
    path.write_bytes(bytes(b))
    return path


@case("rosbag")
def ros1_chunk_declares_4gib(d):
    return _info(_ros1_chunk_size(d / "a.bag", 0xFFFFFFF0))


@case("rosbag")
def ros1_bz2_chunk_expands_beyond_its_declared_size(d):
    return _info(_ros1_chunk_size(d / "a.bag", 1000))


@case("rosbag")
def ros1_lz4_chunk_expands_beyond_its_declared_size(d):
    return _info(_ros1_chunk_size(d / "a.bag", 1000, "lz4"))


for _ext in (".txt", ".h5", ".zip", ".bin"):
    def _mk(ext):
        def fn(d):
            return _info(_ros1_bag(d / ("renamed" + ext)), 20)
        fn.__name__ = f"ros1_bag_renamed_{ext[1:]}"
        return fn
    case("rosbag", "ok")(_mk(_ext))


# -- capture journal (capture recover) ----------------------------------------------------------
def _journal(d, records):
    from hybridhdr.capture import recorder as J
    jp = d / "rec.h5.journal"
    hdr = {"format": "hybridhdr-journal", "version": 1, "sensor_height": 48, "sensor_width": 64, "metadata": {}}
    w = J.JournalWriter(jp, hdr, compression=None)
    for rtype, payload, raw_len in records:
        head = struct.pack("<IBBHQQI", J._SYNC, rtype, 1 if raw_len is not None else 0, 0, len(payload),
                           len(payload) if raw_len is None else raw_len, zlib.crc32(payload))
        w._f.write(head + struct.pack("<I", zlib.crc32(head)) + payload)
    w.close()
    return jp


def _recover_argv(d):
    return ["capture", "recover", str(d / "rec.h5"), "--out", str(d / "out.h5")]


@case("journal", "ok")
def journal_frame_overflowing_time(d):
    from hybridhdr.capture import recorder as J
    meta = json.dumps({"t_start_us": 10**30, "t_end_us": 1, "exposure_us": 1, "shape": [2, 2], "dtype": "|u1",
                       "sequence": 0}).encode()
    _journal(d, [(J.T_FRAME, struct.pack("<I", len(meta)) + meta + b"\0" * 4, None)])
    return _recover_argv(d), lambda out: ("undecodable record" in out, out[-300:])


@case("journal", "ok")
def journal_lz4_declares_2_pow_60(d):
    from hybridhdr.capture import recorder as J
    _journal(d, [(J.T_EVENTS, b"\0" * 64, 1 << 60)])
    return _recover_argv(d), lambda out: ("undecodable record" in out, out[-300:])


@case("journal", "ok")
def journal_frame_nan_pixels(d):
    from hybridhdr.capture import recorder as J
    meta = json.dumps({"t_start_us": 0, "t_end_us": 1, "exposure_us": 1, "shape": [2, 2], "dtype": "<f4",
                       "sequence": 0}).encode()
    _journal(d, [(J.T_FRAME, struct.pack("<I", len(meta)) + meta + np.full(4, np.nan, np.float32).tobytes(), None)])
    return _recover_argv(d), lambda out: ("undecodable record" in out, out[-300:])


@case("journal")
def journal_header_sensor_65536(d):
    from hybridhdr.capture import recorder as J
    jp = d / "rec.h5.journal"
    w = J.JournalWriter(jp, {"sensor_height": 65536, "sensor_width": 65536}, compression=None)
    w.close()
    return _recover_argv(d), None


# -- trust decisions and resource bounds beyond the readers ------------------------------------
_BENCH_HEAD = """[bench]
name = "t"
jod = false
warmup = false

[[datasets]]
kind = "procedural"
width = 32
height = 24
duration_us = 60000
"""


def _bench(d, text, extra_files=()):
    for name in extra_files:
        (d / name).write_bytes(b"not a checkpoint")
    b = d / "b.toml"
    b.write_text(text)
    return ["evaluate", "bench", str(b), "--out", str(d / "o"), "--workers", "0", "--no-progress"]


def _nothing_at(*paths):
    return lambda out: (not any(Path(p).exists() for p in paths), f"left {[str(p) for p in paths if Path(p).exists()]}")


@case("bench")
def bench_grid_sets_allow_pickle(d):
    return _bench(d, _BENCH_HEAD + '[[methods]]\nmethod = "e2vid"\nparams = { weights = "evil.pth" }\n'
                  'grid = { "params.allow_pickle" = [true] }\n', ["evil.pth"]), _nothing_at(d / "o")


@case("bench")
def bench_method_grid_sets_allow_pickle(d):
    t = _BENCH_HEAD + 'method_grid = { "params.allow_pickle" = [true] }\n[[methods]]\nmethod = "e2vid"\n' \
                      'params = { weights = "evil.pth" }\n'
    return _bench(d, t, ["evil.pth"]), _nothing_at(d / "o")


@case("bench")
def bench_grid_params_table_allow_pickle(d):
    t = _BENCH_HEAD + '[[methods]]\nmethod = "e2vid"\ngrid = { params = [{ weights = "evil.pth", allow_pickle = true }] }\n'
    return _bench(d, t, ["evil.pth"]), _nothing_at(d / "o")


@case("bench")
def bench_grid_weights_outside_folder(d):
    return _bench(d, _BENCH_HEAD + '[[methods]]\nmethod = "e2vid"\ngrid = { "params.weights" = ["/etc/passwd"] }\n'), None


@case("bench")
def bench_method_grid_weights_outside_folder(d):
    t = _BENCH_HEAD + 'method_grid = { "params.weights" = ["../../../../etc/passwd"] }\n[[methods]]\nmethod = "e2vid"\n'
    return _bench(d, t), None


@case("bench")
def bench_duration_9e18(d):
    return _bench(d, _BENCH_HEAD.replace("duration_us = 60000", "duration_us = 9e18") + '[[methods]]\nmethod = "akf"\n'), None


@case("bench")
def bench_grid_of_4e6_runs(d):
    vals = ", ".join(str(0.5 + i * 1e-4) for i in range(2000))
    t = _BENCH_HEAD + f'[[methods]]\nmethod = "akf"\ngrid = {{ threshold_factor = [{vals}], "params.x" = [{vals}] }}\n'
    return _bench(d, t), None


@case("bench")
def bench_nested_toml_100k(d):
    return _bench(d, "a = " + "[" * 100_000 + "\n"), None


@case("bench")
def bench_unknown_charts_table(d):
    return _bench(d, _BENCH_HEAD + '[[methods]]\nmethod = "akf"\n[charts.speed_acuracy]\nx = "mse"\n'), None


@case("bench")
def bench_every_run_failed_exits_1(d):
    t = _BENCH_HEAD + '[[methods]]\nmethod = "akf"\nparams = { contrast_threshold = -1.0 }\n'
    return _bench(d, t), None


@case("bench", "usage")
def bench_workers_1000(d):
    return _bench(d, _BENCH_HEAD + '[[methods]]\nmethod = "akf"\n')[:-3] + ["--workers", "1000"], None


# scenes: numbers bounded before anything is built, files read only when regular and bounded
_SCENE = """name = "s"
duration_us = 100000
[render]
spp = 1
[camera]
width = 32
height = 24
fov_deg = 60.0
[[camera.keyframes]]
t_us = 0
position = [0.0, 0.0, -3.0]
look_at = [0.0, 0.0, 0.0]
[[emitters]]
type = "point"
position = [0.0, 3.0, -1.0]
intensity = 10.0
[[objects]]
name = "ball"
mesh = { type = "sphere", radius = 0.5, subdivisions = 2 }
material = { reflectance = 0.5 }
"""


def _scene(d, text=_SCENE, extra=()):
    p = d / "s.toml"
    p.write_text(text)
    return ["simulate", str(p), "--out", str(d / "r.h5"), "--no-progress", *extra], _nothing_at(d / "r.h5")


@case("scene")
def scene_duration_9e18(d):
    return _scene(d, _SCENE.replace("duration_us = 100000", "duration_us = 9000000000000000000"))


@case("scene")
def simulate_duration_s_1e12(d):
    return _scene(d, extra=("--duration-s", "1e12"))


@case("scene")
def scene_sphere_subdivisions_30(d):
    return _scene(d, _SCENE.replace("subdivisions = 2", "subdivisions = 30"))


@case("scene")
def scene_spp_1e9(d):
    return _scene(d, _SCENE.replace("spp = 1", "spp = 1000000000"))


@case("scene")
def scene_nested_toml_100k(d):
    return _scene(d, _SCENE + "x = " + "{a=" * 50_000 + "1" + "}" * 50_000 + "\n")


@case("scene", "usage")
def simulate_width_65536(d):
    return _scene(d, extra=("--width", "65536"))


@case("scene")
def scene_texture_png_bomb(d):
    _png_header_only(d / "t.png", 100_000, 100_000)
    return _scene(d, _SCENE.replace("reflectance = 0.5", 'reflectance = { texture = "t.png" }'))


@case("scene")
def scene_texture_is_a_fifo(d):
    os.mkfifo(d / "t.png")
    return _scene(d, _SCENE.replace("reflectance = 0.5", 'reflectance = { texture = "t.png" }'))


@case("scene")
def scene_calibration_is_a_fifo(d):
    os.mkfifo(d / "cal.json")
    return _scene(d, _SCENE.replace("fov_deg = 60.0", 'calibration = "cal.json"').replace("width = 32\nheight = 24\n", ""))


@case("scene")
def simulate_out_is_the_scene(d):
    argv, _ = _scene(d)
    argv[argv.index("--out") + 1] = str(d / "s.toml")
    return argv, lambda out: ((d / "s.toml").read_text() == _SCENE, "the scene file was replaced")


# HDF5 files that would make a reader open other files
def _ext_frames(d, how):
    import h5py
    p = _container(d / "r.h5")
    src = d / "outside.bin"
    src.write_bytes(bytes(range(256)) * 48)
    with h5py.File(p, "a") as f:
        g = f.create_group("frames")
        if how == "external":
            g.create_dataset("images", shape=(4, 48, 64), dtype="u1", external=[(str(src), 0, 4 * 48 * 64)])
        elif how == "virtual":
            lay = h5py.VirtualLayout(shape=(4, 48, 64), dtype="u1")
            lay[:] = h5py.VirtualSource(str(d / "missing.h5"), "data", shape=(4, 48, 64))
            g.create_virtual_dataset("images", lay, fillvalue=7)
        g["t_start_us"] = np.arange(4) * 10
        g["t_end_us"] = np.arange(4) * 10 + 5
        if how == "link":
            del f["frames"]
            f["frames"] = h5py.ExternalLink(str(d / "other.h5"), "/frames")
    return p


@case("hybridhdr")
def container_frames_in_external_raw_storage(d):
    return ["convert", str(_ext_frames(d, "external")), str(d / "out.h5")], _nothing_at(d / "out.h5")


@case("hybridhdr")
def container_frames_virtual_dataset_missing_source(d):
    return ["convert", str(_ext_frames(d, "virtual")), str(d / "out.h5")], _nothing_at(d / "out.h5")


@case("hybridhdr")
def container_frames_external_link(d):
    import h5py
    with h5py.File(d / "other.h5", "w") as f:
        f["frames/images"] = np.zeros((1, 48, 64), np.uint8)
    return _info(_ext_frames(d, "link"))


@case("dsec")
def dsec_events_external_link(d):
    import h5py
    with h5py.File(d / "other.h5", "w") as f:
        for name in "xytp":
            f[f"events/{name}"] = np.zeros(10, np.uint16 if name in "xy" else np.uint32 if name == "t" else np.uint8)
    p = d / "events.h5"
    with h5py.File(p, "w") as f:
        f["events"] = h5py.ExternalLink(str(d / "other.h5"), "/events")
        f["t_offset"] = np.int64(0)
        f["ms_to_idx"] = np.zeros(4, np.uint64)
    return ["info", str(p), "--json", "--from", "dsec"], None


@case("akf_mat")
def mat73_events_external_storage(d):
    src = d / "outside.bin"
    src.write_bytes(np.ones((4, 2)).tobytes())
    p = _mat73(d / "a.mat", None, None, {"im_height": 48, "im_width": 64})
    import h5py
    with h5py.File(p, "a") as f:
        ds = f.create_dataset("events", shape=(4, 2), dtype="<f8", external=[(str(src), 0, 64)])
        ds.attrs["MATLAB_class"] = np.bytes_(b"double")
    return ["info", str(p), "--json", "--from", "akf_mat"], None


# files named by data files: inside their folder only
@case("ecd")
def ecd_images_txt_absolute_path(d):
    _png_header_only(d / "outside.png", 10, 7)
    return _info(_ecd_folder(d / "ecd", images_txt=f"0.0 {d / 'outside.png'}\n"))


@case("brackets")
def brackets_image_list_absolute_path(d):
    from PIL import Image
    b = d / "br"
    b.mkdir()
    for i in range(2):
        Image.fromarray(np.full((8, 8), 60 * (i + 1), np.uint8)).save(b / f"e{i}.png")
    Image.fromarray(np.full((8, 8), 99, np.uint8)).save(d / "outside.png")
    (b / "image_list.txt").write_text(f"e0.png 0.01\n{d / 'outside.png'} 0.02\n")
    return ["calibrate", "hdr-reference", str(b), "--out", str(d / "ref.exr")], _nothing_at(d / "ref.exr")


def _recon_folder(d, timestamps):
    r = d / "recon"
    r.mkdir()
    (r / "timestamps.txt").write_text(timestamps)
    return ["view", str(_container(d / "r.h5")), "--recon", str(r), "--out", str(d / "v.mp4"), "--no-progress"]


@case("view")
def view_recon_timestamps_absolute_exr(d):
    (d / "x.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\0" * 64)
    return _recon_folder(d, f"0 {d / 'x.exr'}\n"), _nothing_at(d / "v.mp4")


@case("view")
def view_recon_timestamps_dotdot_passwd(d):
    return _recon_folder(d, "0 ../../../../../../../etc/passwd\n"), _nothing_at(d / "v.mp4")


# partial outputs: exclusive, never through a link, never a user's folder
@case("partial")
def convert_partial_is_a_symlink(d):
    victim = d / "victim.txt"
    victim.write_text("keep")
    os.symlink(victim, d / "out.raw.partial")
    argv = ["convert", str(_container(d / "r.h5")), str(d / "out.raw"), "--to", "evt3"]
    return argv, lambda out: (victim.read_text() == "keep" and not os.path.lexists(d / "out.raw"),
                              "wrote through the link")


@case("partial")
def convert_ecd_user_folder_named_partial(d):
    user = d / "out.partial"
    user.mkdir()
    (user / "mine.txt").write_text("keep")
    argv = ["convert", str(_container(d / "r.h5")), str(d / "out"), "--to", "ecd"]
    return argv, lambda out: ((user / "mine.txt").read_text() == "keep", "the user's folder was touched")


@case("partial", "ok")
def convert_after_a_killed_run_left_partial(d):
    part = d / "out.h5.partial"
    part.write_bytes(b"half a file")  # no live writer holds it: stale
    os.setxattr(part, "user.hybridhdr.partial", b"pid 999999999 host x")  # the mark a writer of ours puts on it
    argv = ["convert", str(_container(d / "r.h5")), str(d / "out.h5")]
    return argv, lambda out: ((d / "out.h5").is_file() and not (d / "out.h5.partial").exists(), out[-300:])


@case("partial")
def convert_user_file_named_partial(d):
    user = d / "out.h5.partial"
    user.write_text("my notes")  # a user's own file: never taken for an interrupted run's
    argv = ["convert", str(_container(d / "r.h5")), str(d / "out.h5")]
    return argv, lambda out: (user.read_text() == "my notes" and not (d / "out.h5").exists(),
                              "the user's file was deleted")


@case("partial", "ok")
def reconstruct_after_kill9_left_partial_folder(d):
    part = d / "o.partial"
    part.mkdir()
    (part / "frame_000000.exr").write_text("old")
    import socket
    (part / ".hybridhdr-partial").write_text(f"pid 999999999 host {socket.gethostname()} started x\n")
    argv = ["reconstruct", str(_container(d / "r.h5", n=3000)), "--out", str(d / "o"), "--fps", "20", "--no-progress",
            "--method", "highpass"]
    return argv, lambda out: ((d / "o" / "run.json").is_file() and not part.exists(), out[-300:])


# outputs that are inputs
@case("outputs")
def view_still_is_the_recording(d):
    p = _container(d / "r.h5")
    before = p.read_bytes()
    return (["view", str(p), "--still", str(p), "--out", str(d / "v.mp4"), "--no-progress"],
            lambda out: (p.read_bytes() == before and not (d / "v.mp4").exists(), "the recording was replaced"))


@case("outputs")
def convert_output_is_the_input(d):
    p = _container(d / "r.h5")
    before = p.read_bytes()
    return ["convert", str(p), str(p)], lambda out: (p.read_bytes() == before, "the input was replaced")


@case("outputs")
def hdr_reference_out_png(d):
    from PIL import Image
    b = d / "br"
    b.mkdir()
    for i in range(2):
        Image.fromarray(np.full((8, 8), 60 * (i + 1), np.uint8)).save(b / f"e{i}.png")
    (b / "exposures.txt").write_text("e0.png 0.01\ne1.png 0.02\n")
    return ["calibrate", "hdr-reference", str(b), "--out", str(d / "ref.png")], _nothing_at(d / "ref.png")


# declared but unstored: checked before allocation
@case("hybridhdr")
def container_triggers_declared_3e8(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        g = f.require_group("triggers")
        for name, dt in (("t", "<i8"), ("p", "i1"), ("id", "<u2")):
            if name in g:
                del g[name]
            g.create_dataset(name, shape=(3 * 10**8,), dtype=dt, chunks=(1 << 16,), compression="gzip")
    return _info(p)


@case("hybridhdr")
def container_frames_times_declared_4e8(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        g = f.create_group("frames")
        g["images"] = np.zeros((2, 48, 64), np.uint8)
        for name in ("t_start_us", "t_end_us"):
            g.create_dataset(name, shape=(4 * 10**8,), dtype="<i8", chunks=(1 << 16,), compression="gzip")
    return _info(p)


@case("hybridhdr")
def container_frames_gain_wrong_length(d):
    import hybridhdr as hh
    import h5py
    p = _container(d / "r.h5", frames=hh.Frames(np.ones((2, 48, 64), np.uint8), [0, 10], [5, 15]))
    with h5py.File(p, "a") as f:
        f["frames"].create_dataset("gain", shape=(10**8,), dtype="<f8", chunks=(1 << 16,), compression="gzip")
    return _info(p)


@case("hybridhdr")
def container_hdr_t_us_wrong_length(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        g = f.create_group("hdr")
        g["images"] = np.ones((2, 48, 64), np.float32)
        g.create_dataset("t_us", shape=(10**8,), dtype="<i8", chunks=(1 << 16,), compression="gzip")
    return ["convert", str(p), str(d / "o.h5")], _nothing_at(d / "o.h5")


@case("hybridhdr")
def container_zero_frames_beyond_memory_reconstruct(d):
    # 180 Mpx of gzip'd zeros (0.2 MB stored): as float64 in the filter 1.4 GB, more than the
    # runner's address-space cap leaves; a 1 GiB version of this file made the AKF take 7.2 GB
    import h5py
    side, k = 2000, 45
    p = _container(d / "r.h5", n=2000, ss=(side, side))
    with h5py.File(p, "a") as f:
        g = f.create_group("frames")
        ds = g.create_dataset("images", shape=(k, side, side), dtype="u1", chunks=(1, side, side),
                              compression="gzip")
        z = np.zeros((side, side), np.uint8)
        for i in range(k):
            ds[i] = z
        g["t_start_us"] = np.arange(k) * 5000
        g["t_end_us"] = np.arange(k) * 5000 + 100
    return ["reconstruct", str(p), "--out", str(d / "o"), "--fps", "10", "--no-progress"], _nothing_at(d / "o")


# minor silent wrongs
def _frames_dtype(d, arr):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        g = f.create_group("frames")
        g["images"] = arr
        g["t_start_us"] = np.arange(len(arr))
        g["t_end_us"] = np.arange(len(arr)) + 1
    return ["convert", str(p), str(d / "o.h5")], _nothing_at(d / "o.h5")


@case("hybridhdr")
def container_int64_frames_minus_5(d):
    return _frames_dtype(d, np.full((2, 48, 64), -5, np.int64))


@case("hybridhdr")
def container_uint64_frames_2_pow_63(d):
    return _frames_dtype(d, np.full((2, 48, 64), 1 << 63, np.uint64))


@case("hybridhdr")
def container_compound_frames(d):
    return _frames_dtype(d, np.zeros((2, 48, 64), dtype=[("a", "u1"), ("b", "f4")]))


@case("hybridhdr")
def container_sensor_height_33_5(d):
    import h5py
    p = _container(d / "r.h5")
    with h5py.File(p, "a") as f:
        f.attrs["sensor_height"] = 33.5
    return _info(p)


# options and special files
def _rec_argv(d, *extra):
    return ["reconstruct", str(_container(d / "r.h5", n=2000)), "--out", str(d / "o"), "--no-progress", *extra]


@case("options", "usage")
def reconstruct_chunk_events_1(d):
    return _rec_argv(d, "--fps", "10", "--chunk-events", "1"), None


@case("options", "usage")
def reconstruct_writers_1000(d):
    return _rec_argv(d, "--fps", "10", "--writers", "1000"), None


@case("options", "usage")
def view_height_100000(d):
    return ["view", str(_container(d / "r.h5")), "--out", str(d / "v.mp4"), "--height", "100000"], None


@case("special")
def info_fifo_with_from(d):
    os.mkfifo(d / "in.raw")
    return ["info", str(d / "in.raw"), "--from", "evt3"], None


@case("special")
def reconstruct_times_us_fifo(d):
    os.mkfifo(d / "t.txt")
    return _rec_argv(d, "--times-us", str(d / "t.txt")), _nothing_at(d / "o")


@case("special")
def reconstruct_config_fifo(d):
    os.mkfifo(d / "c.toml")
    return _rec_argv(d, "--fps", "10", "--config", str(d / "c.toml")), _nothing_at(d / "o")


@case("special")
def reconstruct_times_us_dev_zero(d):
    return _rec_argv(d, "--times-us", "/dev/zero"), _nothing_at(d / "o")


@case("special")
def reconstruct_config_dev_zero(d):
    return _rec_argv(d, "--fps", "10", "--config", "/dev/zero"), _nothing_at(d / "o")


@case("special")
def reconstruct_profile_dev_zero(d):
    return _rec_argv(d, "--fps", "10", "--profile", "/dev/zero"), _nothing_at(d / "o")


@case("special")
def hdr_reference_crf_dev_zero(d):
    from PIL import Image
    b = d / "br"
    b.mkdir()
    for i in range(2):
        Image.fromarray(np.full((8, 8), 60 * (i + 1), np.uint8)).save(b / f"e{i}.png")
    (b / "exposures.txt").write_text("e0.png 0.01\ne1.png 0.02\n")
    return ["calibrate", "hdr-reference", str(b), "--crf", "/dev/zero", "--out", str(d / "ref.exr")], \
        _nothing_at(d / "ref.exr")


@case("special")
def reconstruct_config_sets_allow_pickle(d):
    (d / "evil.pth").write_bytes(b"payload")
    (d / "run.toml").write_text('weights = "evil.pth"\nallow_pickle = true\n')
    return _rec_argv(d, "--fps", "10", "--method", "e2vid", "--config", str(d / "run.toml")), _nothing_at(d / "o")


# -- an attack on outputs, the bench, sensor profiles and the newer readers -------------------------
_KEEP: list = []  # objects a case's child must find alive (a recorder's journal lock, a running bench's lock)


def _rec_frames(path, frames, n=3000, ss=(24, 32)):
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    return write_recording(hh.Recording(_events(n, ss[1], ss[0], span=200_000), ss, frames), path)


def _flat_frames(k=6, ss=(24, 32), dtype=np.uint8, value=100, t_start=None, t_end=None):
    import hybridhdr as hh
    ts = np.arange(k) * 30_000 if t_start is None else np.asarray(t_start)
    te = ts + 5_000 if t_end is None else np.asarray(t_end)
    return hh.Frames(np.full((k, *ss), value, dtype), ts, te)


def _unchanged(*paths):
    before = {p: Path(p).read_bytes() for p in paths}
    return lambda out: (all(Path(p).read_bytes() == b for p, b in before.items()), "an input was replaced")


@case("outputs")
def capture_sync_report_is_the_recording(d):
    p = _container(d / "r.h5")
    return ["capture", "sync", str(p), "--report", str(p)], _unchanged(p)


@case("outputs")
def capture_sync_out_is_the_recording(d):
    p = _container(d / "r.h5")
    return ["capture", "sync", str(p), "--out", str(p)], _unchanged(p)


@case("outputs")
def calibrate_sensor_out_is_the_recording(d):
    p = _rec_frames(d / "r.h5", _flat_frames())
    return ["calibrate", "sensor", str(p), "--out", str(p)], _unchanged(p)


@case("outputs", "usage")  # an existing output: a usage error (exit 2), as in every verb
def convert_existing_output_without_overwrite(d):
    (d / "o.h5").write_bytes(b"a two-minute simulation")
    return ["convert", str(_container(d / "r.h5")), str(d / "o.h5")], _unchanged(d / "o.h5")


@case("partial", "refused")
def reconstruct_user_file_named_out_partial(d):
    (d / "o.partial").write_text("mine")
    argv = ["reconstruct", str(_container(d / "r.h5", n=2000)), "--out", str(d / "o"), "--fps", "10",
            "--method", "highpass", "--no-progress"]
    return argv, lambda out: ((d / "o.partial").read_text() == "mine", "the user's file was deleted")


@case("outputs")
def capture_recover_while_the_recorder_writes(d):
    from hybridhdr.capture.recorder import JournalWriter, journal_path
    jw = JournalWriter(journal_path(d / "rec.h5"), {"format": "hybridhdr-journal", "version": 1,
                                                     "sensor_height": 48, "sensor_width": 64},
                       compression=None)
    jw.write_events(_events(100))
    jw.flush()
    _KEEP.append(jw)  # a live recorder: it holds the journal's lock
    return (["capture", "recover", str(d / "rec.h5")],
            lambda out: ((d / "rec.h5.journal").is_file() and not (d / "rec.h5").exists(), "recovered a live journal"))


def _bench_out(d, extra=()):
    return _bench(d, _BENCH_HEAD + '[[methods]]\nmethod = "highpass"\n') + list(extra)


@case("bench", "usage")  # a non-empty --out: a usage error (exit 2), as in every verb
def bench_second_run_on_a_non_empty_out(d):
    (d / "o").mkdir()
    (d / "o" / "results.csv").write_text("first bench")
    return _bench_out(d), _unchanged(d / "o" / "results.csv")


@case("bench")
def bench_out_held_by_a_running_bench(d):
    from hybridhdr.evaluate.bench import claim_bench_out
    _KEEP.append(claim_bench_out(d / "o"))
    return _bench_out(d, ["--overwrite"]), _nothing_at(d / "o" / "results.csv")


def _task_file(d, rows=None, raw=None):
    from hybridhdr.evaluate import bench as B
    argv = _bench_out(d)
    bench = B.load_bench(d / "b.toml", out_dir=d / "o")
    tasks = B.expand(bench)
    key = B._task_key(tasks[0], B._bench_opts(bench))
    runs = d / "o" / B.RUNS_DIR
    runs.mkdir(parents=True)
    f = runs / "task_00000.json"
    if raw == "fifo":
        os.mkfifo(f)
    elif raw == "dev_zero":
        os.symlink("/dev/zero", f)
    elif raw is not None:
        f.write_text(raw.replace("KEY", key))
    else:
        f.write_text(json.dumps({"key": key, "task": 0, "rows": rows}))
    return argv + ["--resume"]


def _no_made_up(d):
    def check(out):
        text = (d / "o" / "results.csv").read_text() if (d / "o" / "results.csv").is_file() else ""
        return ("-5.0" not in text and "=cmd" not in text and bool(text)), text[:300]
    return check


@case("bench", "ok")
def bench_resume_tampered_values(d):
    rows = [{"dataset": "procedural0", "method_label": "highpass", "status": "ok", "mse": -5.0, "ssim": 7.0}]
    return _task_file(d, rows), _no_made_up(d)


@case("bench", "ok")
def bench_resume_formula_column(d):
    rows = [{"dataset": "procedural0", "status": "ok", "=cmd|' /C calc'!A0": 1.0}]
    return _task_file(d, rows), _no_made_up(d)


@case("bench", "ok")
def bench_resume_task_file_is_a_fifo(d):
    return _task_file(d, raw="fifo"), _no_made_up(d)


@case("bench", "ok")
def bench_resume_task_file_is_dev_zero(d):
    return _task_file(d, raw="dev_zero"), _no_made_up(d)


@case("bench", "ok")
def bench_resume_task_file_5000_deep(d):
    return _task_file(d, raw='{"key": "KEY", "rows": ' + "[" * 5000 + "]" * 5000 + "}"), _no_made_up(d)


def _sensor_profile(d, **params):
    p = d / "prof.json"
    p.write_text(json.dumps({"format": "hybridhdr-sensor-profile", "version": 1, "name": "x", "sensor": {},
                             "simulator_params": params, "estimates": {}, "provenance": {}}))
    return p


def _simulate_with_profile(d, prof):
    return _scene(d, extra=("--sensor", str(prof)))


@case("profile", "refused")
def profile_photoreceptor_cutoff_1e308(d):
    return _simulate_with_profile(d, _sensor_profile(d, photoreceptor_cutoff_hz=1e308))


@case("profile", "refused")
def profile_thresholds_1e300_refractory_0(d):
    return _simulate_with_profile(d, _sensor_profile(d, contrast_threshold_on=1e-300, contrast_threshold_off=1e-300,
                                                     refractory_period_us=0))


@case("profile", "refused")
def profile_is_a_fifo(d):
    os.mkfifo(d / "prof.json")
    return _simulate_with_profile(d, d / "prof.json")


@case("profile", "refused")
def profile_is_dev_zero(d):
    os.symlink("/dev/zero", d / "prof.json")
    return _simulate_with_profile(d, d / "prof.json")


@case("profile", "refused")
def profile_json_5000_deep(d):
    (d / "prof.json").write_text("[" * 5000 + "]" * 5000)
    return _simulate_with_profile(d, d / "prof.json")


def _hdr_ref_with_meta(d, how):
    from PIL import Image
    b = d / "br"
    b.mkdir()
    for i in range(2):
        Image.fromarray(np.full((8, 8), 60 * (i + 1), np.uint8)).save(b / f"e{i}.png")
    m = b / "brackets.json"
    if how == "fifo":
        os.mkfifo(m)
    elif how == "dev_zero":
        os.symlink("/dev/zero", m)
    else:
        m.write_text('{"format": ' + "[" * 5000 + "]" * 5000 + "}")
    return ["calibrate", "hdr-reference", str(b), "--out", str(d / "ref.exr")], _nothing_at(d / "ref.exr")


@case("brackets")
def brackets_json_is_a_fifo(d):
    return _hdr_ref_with_meta(d, "fifo")


@case("brackets")
def brackets_json_is_dev_zero(d):
    return _hdr_ref_with_meta(d, "dev_zero")


@case("brackets")
def brackets_json_5000_deep(d):
    return _hdr_ref_with_meta(d, "deep")


def _recon_exr(d, ss=(48, 64), run_json=None):
    from hybridhdr.formats.images import write_exr
    r = d / "recon"
    r.mkdir()
    write_exr(r / "frame_000000.exr", np.ones(ss, np.float32))
    (r / "timestamps.txt").write_text("0 frame_000000.exr\n")
    if run_json == "fifo":
        os.mkfifo(r / "run.json")
    elif run_json == "dev_zero":
        os.symlink("/dev/zero", r / "run.json")
    elif run_json == "deep":
        (r / "run.json").write_text("[" * 5000 + "]" * 5000)
    return ["view", str(_container(d / "r.h5")), "--recon", str(r), "--out", str(d / "v.mp4"), "--no-progress"]


@case("view", "refused")
def view_recon_of_another_size(d):
    return _recon_exr(d, ss=(30, 40)), _nothing_at(d / "v.mp4")


@case("view")
def view_recon_run_json_is_a_fifo(d):
    return _recon_exr(d, run_json="fifo"), _nothing_at(d / "v.mp4")


@case("view")
def view_recon_run_json_is_dev_zero(d):
    return _recon_exr(d, run_json="dev_zero"), _nothing_at(d / "v.mp4")


@case("view")
def view_recon_run_json_5000_deep(d):
    return _recon_exr(d, run_json="deep"), _nothing_at(d / "v.mp4")


def _thresholds_case(d, make):
    t = d / "t.npz"
    make(t)
    argv = ["reconstruct", str(_rec_frames(d / "r.h5", _flat_frames())), "--out", str(d / "o"), "--fps", "20",
            "--thresholds", str(t), "--no-progress"]
    return argv, _nothing_at(d / "o")


def _npz_c(c):
    return lambda t: np.savez(t, format=np.array("hybridhdr-thresholds"), version=np.array(1),
                              c_on=np.full((24, 32), c), c_off=np.full((24, 32), c), fallback_on=np.array(0.2),
                              fallback_off=np.array(0.2))


def _npz_declaring_30000sq(t):
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": (30000, 30000)})
    with zipfile.ZipFile(t, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("c_on.npy", "w", force_zip64=True) as f:
            f.write(hdr.getvalue())
            f.write(b"\0" * (7 << 20))


@case("thresholds", "refused")
def thresholds_c_1e308_writes_no_inf_exr(d):
    return _thresholds_case(d, _npz_c(1e308))


@case("thresholds", "refused")
def thresholds_c_1e_minus_300(d):
    return _thresholds_case(d, _npz_c(1e-300))


@case("thresholds", "refused")
def thresholds_npz_declares_30000sq(d):
    return _thresholds_case(d, _npz_declaring_30000sq)


@case("thresholds", "refused")
def thresholds_npz_zip_magic_only(d):
    return _thresholds_case(d, lambda t: t.write_bytes(b"PK\x03\x04" + bytes(range(256))))


@case("thresholds", "refused")
def thresholds_npz_is_a_fifo(d):
    return _thresholds_case(d, lambda t: os.mkfifo(t))


@case("frames", "refused")
def reconstruct_16bit_frames_without_profile(d):
    p = _rec_frames(d / "r.h5", _flat_frames(dtype=np.uint16, value=40000))
    return ["reconstruct", str(p), "--out", str(d / "o"), "--fps", "20", "--no-progress"], _nothing_at(d / "o")


@case("frames", "ok")
def reconstruct_sorted_starts_unsorted_mids(d):
    ts = np.array([0, 30_000, 40_000, 90_000, 120_000, 150_000])
    te = ts + 5_000
    te[1] = 80_000
    p = _rec_frames(d / "r.h5", _flat_frames(t_start=ts, t_end=te))
    return (["reconstruct", str(p), "--out", str(d / "o"), "--fps", "50", "--no-progress"],
            lambda out: ((d / "o" / "run.json").is_file(), out[-300:]))


@case("frames", "refused")
def overexpose_every_frame_at_one_instant(d):
    ts = np.zeros(6, np.int64)
    p = _rec_frames(d / "r.h5", _flat_frames(t_start=ts, t_end=ts + 5000))
    return (["evaluate", "overexpose", str(p), "--gain", "4", "--method", "akf", "--out", str(d / "e"),
             "--no-progress", "--no-figures"], _nothing_at(d / "e"))


@case("options", "refused")
def reconstruct_quiet_prints_its_error(d):
    (d / "bad.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 64)  # a broken file: an error to report
    return ["reconstruct", str(d / "bad.h5"), "--out", str(d / "o"), "--fps", "10", "-q"], _nothing_at(d / "o")


# -- runner (fork server) -----------------------------------------------------------------------
def _preload():
    import hybridhdr.cli  # noqa: F401
    from hybridhdr.formats import formats
    formats()  # imports every format module
    import hybridhdr.capture.cli  # noqa: F401
    import hybridhdr.capture.recorder  # noqa: F401
    for m in ("PIL.Image", "PIL.PngImagePlugin", "lz4.frame", "lz4.block", "zstandard", "rosbags.highlevel",
              "scipy.io", "tqdm"):
        try:
            __import__(m)
        except ImportError:
            pass
    # compile/load the numba kernels once, here, not in every child
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    with tempfile.TemporaryDirectory() as t:
        p = write_recording(hh.Recording(_events(10), (48, 64)), Path(t) / "w.h5")
        for fmt, name in (("evt2", "a.raw"), ("evt3", "b.raw"), ("dat", "c.dat"), ("ecd", "e")):
            hh.write(hh.read(p), Path(t) / name, fmt)
            hh.read(Path(t) / name)


def _vm_size() -> int:
    with open("/proc/self/status") as f:
        for ln in f:
            if ln.startswith("VmSize:"):
                return int(ln.split()[1]) * 1024
    return 0


def _run_child(argv, out_path, err_path, mem_bytes):
    pid = os.fork()
    if pid == 0:  # child
        code = 70
        try:
            fo = os.open(out_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            fe = os.open(err_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            os.dup2(fo, 1)
            os.dup2(fe, 2)
            sys.stdout = io.TextIOWrapper(os.fdopen(1, "wb", buffering=0), write_through=True)
            sys.stderr = io.TextIOWrapper(os.fdopen(2, "wb", buffering=0), write_through=True)
            lim = _vm_size() + mem_bytes
            resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
            from hybridhdr.cli import main
            code = int(main(argv) or 0)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 2
        except BaseException:
            try:
                traceback.print_exc()
            except BaseException:
                pass
            code = 70
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            except BaseException:
                pass
            os._exit(code)
    return pid


def _wait(pid, timeout):
    t_end = time.monotonic() + timeout
    while True:
        wpid, status, ru = os.wait4(pid, os.WNOHANG)
        if wpid == pid:
            return status, ru, False
        if time.monotonic() > t_end:
            os.kill(pid, signal.SIGKILL)
            _, status, ru = os.wait4(pid, 0)
            return status, ru, True
        time.sleep(0.005)


def run_cases(quick=True, timeout=None, mem_gib=1.5, selected=None, log=None):
    """Run every case; returns ``(table, rows)``: per-reader counts and one row per case."""
    _preload()
    timeout = timeout or (20.0 if quick else 120.0)
    table: dict[str, dict[str, int]] = {}
    rows = []
    with tempfile.TemporaryDirectory(prefix="hybridhdr-hostile-") as base:
        for k, (reader, name, builder, expect) in enumerate(CASES):
            if selected and not any(s in name for s in selected):
                continue
            d = Path(base) / f"{k:03d}_{name}"
            d.mkdir()
            t_build = time.perf_counter()
            argv, check = builder(d)
            t0 = time.perf_counter()
            out_p, err_p = d / "_stdout", d / "_stderr"
            pid = _run_child(argv, out_p, err_p, int(mem_gib * (1 << 30)))
            status, ru, hung = _wait(pid, timeout)
            dt = time.perf_counter() - t0
            out = out_p.read_text(errors="replace")
            err = err_p.read_text(errors="replace")
            rss_mb = ru.ru_maxrss / 1024
            if hung:
                outcome = "hang"
            elif os.WIFSIGNALED(status):
                outcome = "crash"
            else:
                rc = os.WEXITSTATUS(status)
                err_lines = [ln for ln in err.splitlines() if "error:" in ln]
                if "Traceback" in err or rc == 70:
                    outcome = "traceback"
                elif rc == 1 and len(err_lines) == 1:
                    outcome = "clean" if expect in ("error", "refused") else "silent"
                    if outcome == "clean" and check is not None:  # e.g. nothing written, a file untouched
                        good, why = check(out + err)
                        outcome = "clean" if good else "silent"
                elif rc == 2 and len(err_lines) == 1 and expect in ("usage", "refused"):
                    # an option out of range: argparse's usage error (exit 2), one line; "refused": a
                    # refusal the verb may report as a usage error (2) or an error (1)
                    outcome = "clean"
                    if check is not None:
                        good, why = check(out + err)
                        outcome = "clean" if good else "silent"
                elif rc == 0:
                    if expect == "error":
                        outcome = "silent"
                    else:
                        good, why = check(out + err) if check else (True, "")
                        outcome = "ok" if good else "silent"
                else:
                    outcome = "traceback"
            row = {"reader": reader, "case": name, "expect": expect, "outcome": outcome,
                   "seconds": round(dt, 3), "build_s": round(t0 - t_build, 3), "peak_rss_mb": round(rss_mb, 1),
                   "message": (err.strip().splitlines() or [""])[-1][:300]}
            rows.append(row)
            t = table.setdefault(reader, dict.fromkeys(COLUMNS, 0))
            t["tried"] += 1
            t[outcome] += 1
            if log is not None:
                print(f"{outcome:<9} {reader:<9} {name:<42} {dt:6.2f}s {rss_mb:7.1f} MB  {row['message'][:110]}",
                      file=log, flush=True)
    return table, rows


def format_table(table) -> str:
    lines = [f"{'reader':<10}" + "".join(f"{c:>10}" for c in COLUMNS)]
    tot = dict.fromkeys(COLUMNS, 0)
    for r in sorted(table):
        lines.append(f"{r:<10}" + "".join(f"{table[r][c]:>10}" for c in COLUMNS))
        for c in COLUMNS:
            tot[c] += table[r][c]
    lines.append(f"{'total':<10}" + "".join(f"{tot[c]:>10}" for c in COLUMNS))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short timeout per case (20 s)")
    ap.add_argument("--json", action="store_true", help="print only the JSON summary")
    ap.add_argument("--mem-gib", type=float, default=1.5, help="RLIMIT_AS headroom above the address space at fork")
    ap.add_argument("-k", action="append", default=None, help="run only cases whose name contains this")
    a = ap.parse_args(argv)
    table, rows = run_cases(quick=a.quick, mem_gib=a.mem_gib, selected=a.k, log=None if a.json else sys.stderr)
    if not a.json:
        print(format_table(table))
    bad = sum(t["traceback"] + t["crash"] + t["hang"] + t["silent"] for t in table.values())
    print(json.dumps({"table": table, "cases": rows, "bad": bad,
                      "max_peak_rss_mb": max((r["peak_rss_mb"] for r in rows), default=0),
                      "max_seconds": max((r["seconds"] for r in rows), default=0)}))
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
