"""``hybridhdr reconstruct`` outputs: the streaming writer pipeline, OUT.partial semantics, umask,
full disks, exact preview percentiles, playback rate."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hybridhdr.cli import main
from hybridhdr.formats import images as IM
from hybridhdr.reconstruct import output as O
from hybridhdr.reconstruct.api import Video

from .conftest import ideal_recording

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def rec_path(tmp_path_factory):
    from hybridhdr.formats.container import write_recording
    d = tmp_path_factory.mktemp("rec")
    rec, _ = ideal_recording(height=18, width=23)  # odd width: MP4 padding
    write_recording(rec, d / "rec.h5")
    return d / "rec.h5"


def _video(k=12, h=9, w=11, colour=False, seed=0):
    rng = np.random.default_rng(seed)
    shape = (k, h, w, 3) if colour else (k, h, w)
    fr = np.exp(rng.normal(-2, 1.5, shape)).astype(np.float32)
    fr.reshape(-1)[:5] = [1e-7, np.nan, np.inf, 0.0, 1e-6]  # floor, NaN, +inf
    return Video(fr, np.arange(k, dtype=np.int64) * 1000 + 7)


def _tree(d: Path) -> dict:
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("seed", range(6))
def test_log_percentiles_exact(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000))
    x = np.exp(rng.normal(-3, 4, n)).astype(np.float32)
    if seed % 2:
        x[rng.integers(0, n, n // 10 + 1)] = rng.choice([np.nan, np.inf, 0, 1e-8, 1e-6, -1.0, 2e6])
    if seed == 4:
        x[:] = 0.25  # one value
    lp = IM.LogPercentiles()
    parts = np.array_split(x, 5)
    for p in parts:
        lp.add(p)
    for q in ((1.0, 99.0), (0, 100), (37.3, 62.9), (0.001, 99.999)):
        got = lp.limits(lambda: iter(parts[::-1]), *q)
        f = x.astype(np.float64)
        lg = np.log(f[np.isfinite(f) & (f > 1e-6)])  # tone_map's valid pixels (finite, > 0)
        want = tuple(float(v) for v in np.percentile(lg, list(q)))
        assert got == want, (q, got, want)


@pytest.mark.parametrize("colour", [False, True])
def test_pipeline_bit_identical_to_serial_and_in_memory(tmp_path, colour):
    v = _video(colour=colour)
    outs = {}
    for name, kw in {"serial": dict(writers=0), "process": dict(writers=2, queue_frames=1),
                     "thread": dict(writers=3, backend="thread")}.items():
        d = tmp_path / name
        d.mkdir()
        counted = []
        res = O.write_video(v, d, png=True, mp4=True, on_written=counted.append, **kw)
        assert res["exr"] == res["png"] == len(v) and res["mp4"] == "preview.mp4"
        assert sum(counted) == 3 * len(v)  # EXR, PNG, MP4 frames
        outs[name] = _tree(d)
    assert outs["serial"].keys() == outs["process"].keys() == outs["thread"].keys()
    assert not [k for k in outs["serial"] if "spill" in k or "partial" in k]
    for k in outs["serial"]:
        assert outs["process"][k] == outs["serial"][k], k
        assert outs["thread"][k] == outs["serial"][k], k
    # the same EXR bytes and values as the in-memory writer, the same previews as tone_map of the whole video
    IM.write_exr_sequence(v, tmp_path / "mem")
    IM.write_png_previews(v, tmp_path / "mem" / "previews")
    mem = _tree(tmp_path / "mem")
    for k, b in mem.items():
        assert outs["serial"][k] == b, k
    got = IM.read_exr(tmp_path / "serial" / "frame_000003.exr")
    np.testing.assert_array_equal(got, v.frames[3])
    assert got.shape == v.frames.shape[1:]
    ts = (tmp_path / "serial" / "timestamps.txt").read_text().splitlines()
    assert ts[4].split() == [str(v.t_us[3]), "frame_000003.exr"]


@pytest.mark.parametrize("compression", IM.exr_compressions())
def test_exr_compressions_roundtrip(tmp_path, compression):
    v = _video(k=1, h=40, w=33)
    IM.write_exr(tmp_path / "a.exr", v.frames[0], compression=compression)
    back = IM.read_exr(tmp_path / "a.exr")
    f = np.nan_to_num(v.frames[0], nan=0.5)
    b = np.nan_to_num(back, nan=0.5)
    if compression in IM.LOSSY_EXR_COMPRESSIONS:
        np.testing.assert_allclose(b[np.isfinite(f)], f[np.isfinite(f)], rtol=1e-4)
    else:
        np.testing.assert_array_equal(b, f)
    with pytest.raises(ValueError, match="unknown EXR compression"):
        IM.write_exr(tmp_path / "b.exr", v.frames[0], compression="jpeg")


def test_queue_bounds_frames_in_flight(tmp_path, monkeypatch):
    import threading
    import time
    live, peak = [0], [0]
    lock = threading.Lock()

    def slow(path, img, compression, channel):
        with lock:
            live[0] += 1
            peak[0] = max(peak[0], live[0])
        time.sleep(0.005)
        with lock:
            live[0] -= 1
        return 1

    monkeypatch.setattr(O, "_task_exr", slow)
    w = O.VideoWriter(tmp_path, writers=2, backend="thread", queue_frames=3)
    for i in range(40):
        w.write(i, np.ones((4, 5), np.float32))
        with w._lock:
            assert len(w._pending) <= 3
    w.close()
    assert peak[0] <= 2


def _run(argv, capsys=None):
    rc = main(["reconstruct", *map(str, argv), "--no-progress"])
    return rc


def test_cli_partial_dir_umask_and_playback(rec_path, tmp_path, capsys):
    import imageio_ffmpeg
    out = tmp_path / "o"
    old = os.umask(0o027)
    try:
        assert _run([rec_path, "--out", out, "--fps", "300", "--png", "--mp4", "--playback-fps", "24"]) == 0
    finally:
        os.umask(old)
    assert not (tmp_path / "o.partial").exists()
    files = sorted(p for p in out.rglob("*"))
    assert files and not [p for p in files if "spill" in p.name or "partial" in p.name]
    for p in files:
        assert (p.stat().st_mode & 0o777) == (0o750 if p.is_dir() else 0o640), p
    info = json.loads((out / "run.json").read_text())
    w = info["written"]
    n = info["n_frames"]
    assert w["exr"] == w["png"] == n == len(list(out.glob("frame_*.exr"))) and w["mp4_playback_fps"] == 24
    assert "two_sided" in info and "n_clamped" in info["info"]
    k, secs = imageio_ffmpeg.count_frames_and_secs(str(out / "preview.mp4"))
    assert k == n and k / secs == pytest.approx(24, rel=0.02)  # plays at --playback-fps, not --fps
    # same bytes with the serial single-writer path and an overwrite
    (out / "notes.txt").write_text("mine")
    (out / "frame_999999.exr").write_text("stale")
    assert _run([rec_path, "--out", out, "--fps", "300", "--png", "--mp4", "--playback-fps", "24"]) == 2
    assert "not empty" in capsys.readouterr().err and (out / "frame_999999.exr").exists()
    before = _tree(out)
    ino = out.stat().st_ino
    assert _run([rec_path, "--out", out, "--fps", "300", "--png", "--mp4", "--playback-fps", "24", "--writers", "0",
                 "--overwrite"]) == 0
    after = _tree(out)
    assert out.stat().st_ino == ino and after["notes.txt"] == b"mine" and "frame_999999.exr" not in after
    for k in before:
        if k not in ("run.json", "notes.txt", "frame_999999.exr"):
            assert after[k] == before[k], k
    assert json.loads(after["run.json"])["written"]["backend"] == "serial"


def test_cli_existing_folders(rec_path, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    os.chmod(empty, 0o700)
    ino = empty.stat().st_ino
    assert _run([rec_path, "--out", empty, "--fps", "100", "--no-exr"]) == 0
    assert empty.stat().st_ino == ino and (empty.stat().st_mode & 0o777) == 0o700  # the user's folder kept
    assert sorted(p.name for p in empty.iterdir()) == ["run.json", "timestamps.txt"]
    # a leftover OUT.partial is never deleted
    stale = tmp_path / "x.partial"
    stale.mkdir()
    (stale / "frame_000000.exr").write_text("old")
    assert _run([rec_path, "--out", tmp_path / "x", "--fps", "100"]) == 2
    assert "remove it first" in capsys.readouterr().err
    assert (stale / "frame_000000.exr").read_text() == "old" and not (tmp_path / "x").exists()
    # OUT a file
    (tmp_path / "f").write_text("f")
    assert _run([rec_path, "--out", tmp_path / "f", "--fps", "100"]) == 2
    # bad arguments leave nothing
    assert _run([rec_path, "--out", tmp_path / "b", "--exr-compression", "jpeg"]) == 2
    assert _run([rec_path, "--out", tmp_path / "b", "--playback-fps", "0"]) == 2
    assert _run([rec_path, "--out", tmp_path / "b", "--start-us", "10000000000"]) == 1  # empty window: rc 1
    assert not (tmp_path / "b").exists() and not (tmp_path / "b.partial").exists()


@pytest.mark.parametrize("writers", [0, 2])
@pytest.mark.parametrize("where", ["exr", "spill"])
def test_cli_simulated_full_disk(rec_path, tmp_path, capsys, monkeypatch, writers, where):
    calls = [0]
    if where == "exr":
        real = IM.write_exr

        def failing(path, img, **kw):
            calls[0] += 1
            if calls[0] > 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            return real(path, img, **kw)
        monkeypatch.setattr(O, "write_exr", failing)
        # writer processes would inherit the patch only when forked from this process, which the
        # pool does only while it is single-threaded (not so inside a long test session, where it
        # uses a forkserver): run the pool on threads so the patch is seen either way
        real_pool = O._make_pool
        monkeypatch.setattr(O, "_make_pool", lambda n, backend: real_pool(n, "thread"))
    else:
        real_add = IM.LogPercentiles.add

        def failing_add(self, frame):
            calls[0] += 1
            if calls[0] > 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "spill")
            return real_add(self, frame)
        monkeypatch.setattr(IM.LogPercentiles, "add", failing_add)
    out = tmp_path / "o"
    assert _run([rec_path, "--out", out, "--fps", "300", "--png", "--writers", writers]) == 1
    err = capsys.readouterr().err
    assert "No space left on device" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def _unshare_works() -> str | None:
    if shutil.which("unshare") is None:
        return "unshare(1) is not installed"
    try:
        r = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /tmp && echo ok"],
                           capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"unshare failed to run ({e})"
    if r.returncode != 0 or "ok" not in r.stdout:
        return f"cannot mount a tmpfs in a user namespace here ({r.stderr.strip()[:200]})"
    return None


@pytest.mark.skipif(_unshare_works() is not None, reason=f"needs a tmpfs in a user namespace: {_unshare_works()}")
@pytest.mark.parametrize("extra", [[], ["--writers", "0"], ["--no-exr", "--mp4", "--png"]])
def test_cli_full_tmpfs(rec_path, tmp_path, extra):
    mount = tmp_path / "mnt"
    mount.mkdir()
    script = (f'mount -t tmpfs -o size=600k tmpfs "{mount}" || exit 99; '
              f'"$@"; rc=$?; echo "@@rc=$rc"; ls -A "{mount}" | sed "s/^/@@file=/"; exit 0')
    argv = [sys.executable, "-m", "hybridhdr", "reconstruct", str(rec_path), "--out", str(mount / "out"),
            "--fps", "20000", "--no-progress", *extra]
    r = subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", *argv], capture_output=True, text=True,
                       timeout=300, cwd=REPO)
    assert "@@rc=" in r.stdout, r.stdout + r.stderr
    rc = int(r.stdout.split("@@rc=")[1].split()[0])
    files = [ln[len("@@file="):] for ln in r.stdout.splitlines() if ln.startswith("@@file=")]
    errs = [ln for ln in r.stderr.splitlines() if "error:" in ln]
    assert rc == 1 and len(errs) == 1 and "No space left on device" in errs[0], r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    assert files == [], files


def test_cli_sigterm_removes_partial(rec_path, tmp_path):
    import signal
    import time
    out = tmp_path / "o"
    p = subprocess.Popen([sys.executable, "-m", "hybridhdr", "reconstruct", str(rec_path), "--out", str(out),
                          "--fps", "50000", "--png", "--no-progress"], cwd=REPO, stderr=subprocess.PIPE, text=True)
    part = tmp_path / "o.partial"
    t0 = time.time()
    while time.time() - t0 < 120 and not (part.is_dir() and len(list(part.glob("frame_*.exr"))) > 20):
        if p.poll() is not None:
            break
        time.sleep(0.05)
    if p.poll() is not None:
        p.communicate()
        pytest.skip("the run finished before it could be interrupted")
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("hdr", [False, True])
def test_previews_linear_for_a_low_range_video_log_for_hdr(tmp_path, hdr):
    """A video within the clip level is previewed linearly (display gamma 2.2, as `view` shows it):
    its dark tail stays dark; an HDR video (above the clip level, > 100x end to end) gets the log map."""
    from hybridhdr.formats.images import LOG_MAP_RATIO
    from hybridhdr.reconstruct import output as O
    rng = np.random.default_rng(0)
    frames = rng.uniform(0.02, 0.45, (6, 12, 16)).astype(np.float32)  # codes ~ 5-115 of 255, linear
    if hdr:
        frames[:, :4] *= 400.0  # a bright region far above the clip level
    w = O.VideoWriter(tmp_path, exr=False, png=True, writers=0)
    for i, f in enumerate(frames):
        w.write(1000 * i, f)
    info = w.close()
    d = info["preview_display"]
    from imageio.v3 import imread
    png = imread(tmp_path / "previews" / "preview_000000.png")
    if hdr:
        assert d["mode"] == "log" and np.exp(d["limits"][1]) > LOG_MAP_RATIO * np.exp(d["limits"][0])
    else:
        assert d == {"mode": "linear", "hi": 1.0, "gamma": 2.2}
        want = np.round(255 * np.clip(frames[0], 0, 1) ** (1 / 2.2)).astype(np.uint8)
        np.testing.assert_array_equal(png, want)  # the log map put this video's darkest pixel at 0, its p99 at 255


def test_cli_device_line_and_run_json(rec_path, tmp_path, capsys):
    """--device: one line on stderr says which device ran, and run.json records it; without a GPU
    'auto' runs on the CPU and 'cuda' is a usage error naming why."""
    from hybridhdr.reconstruct.cuda import cuda_unavailable_reason
    out = tmp_path / "d"
    assert _run([rec_path, "--out", out, "--device", "cpu", "--no-exr"]) == 0
    err = capsys.readouterr().err
    # the AKF's line also names the CPU engine (one worker: the row-band engine's serial filter)
    want = "device: cpu (requested); cpu engine: row-band (1 worker)"
    assert [ln for ln in err.splitlines() if ln.startswith("device:")] == [want]
    assert json.loads((out / "run.json").read_text())["device"] == want
    if cuda_unavailable_reason() is not None:
        assert _run([rec_path, "--out", tmp_path / "a", "--device", "auto", "--no-exr"]) == 0
        line = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("device:")]
        assert len(line) == 1 and line[0].startswith("device: cpu (auto: ")
        assert json.loads((tmp_path / "a" / "run.json").read_text())["device"] == line[0]
        assert _run([rec_path, "--out", tmp_path / "c", "--device", "cuda", "--no-exr"]) != 0
        assert "device 'cuda' requested but" in capsys.readouterr().err
