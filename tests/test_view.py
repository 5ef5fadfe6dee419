"""Previews users can watch: the robust preview tone map and ``hybridhdr view``."""

import re

import numpy as np
import pytest

from hybridhdr.formats.images import LogPercentiles, tone_map


def test_tone_map_ignores_bad_pixels():
    rng = np.random.default_rng(0)
    img = np.exp(rng.normal(0, 1, (4, 60, 80))).astype(np.float32)
    ref, lim = tone_map(img)
    bad = img.copy()
    idx = rng.random(bad.shape) < 0.05  # 5 % clamped / broken pixels: more than the 1 % percentile tail
    bad[idx] = rng.choice(np.array([np.nan, np.inf, -np.inf, 0.0, 1e-6, -3.0], np.float32), int(idx.sum()))
    out, lim2 = tone_map(bad)
    assert abs(lim2[0] - lim[0]) < 0.1 and abs(lim2[1] - lim[1]) < 0.1  # the old map pinned lo at log 1e-6
    good = ~idx
    assert np.abs(out[good].astype(int) - ref[good].astype(int)).max() <= 8
    assert np.all(out[np.isnan(bad) | (bad <= 1e-6) | np.isneginf(bad)] == 0) and np.all(out[np.isposinf(bad)] == 255)
    # the streaming writer's exact percentiles agree bit for bit
    lp = LogPercentiles()
    for fr in bad:
        lp.add(fr)
    assert lp.limits(lambda: iter(bad)) == lim2
    # nothing valid at all: black, no error
    u8, _ = tone_map(np.full((2, 3), np.nan))
    assert not u8.any()


def _decode(path):
    """(frames as (H, W, 3) uint8, {"size": (w, h), "fps": playback rate}) through an ffmpeg run of our own
    (imageio_ffmpeg.read_frames leaves its pipes open when ffmpeg has already exited)."""
    import subprocess

    import imageio_ffmpeg
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(path))
    probe = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-i", str(path)], capture_output=True, text=True)
    w, h = (int(v) for v in re.search(r"Video:.*?, (\d+)x(\d+)", probe.stderr).groups())
    raw = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(path), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], capture_output=True, check=True).stdout
    frames = list(np.frombuffer(raw, np.uint8).reshape(-1, h, w, 3))
    assert len(frames) == n
    return frames, {"size": (w, h), "fps": n / secs}


def test_view_colours_panels_and_time_bar(tmp_path, capsys):
    import json

    import hybridhdr as hh
    from hybridhdr.cli import main
    from hybridhdr.formats.container import write_recording
    from hybridhdr.view import BAR_HEIGHT, BACKGROUND, LABEL_HEIGHT, OFF_COLOUR, ON_COLOUR
    from PIL import Image
    # 40x30 sensor; ON events at (5, 5) in every 100 ms window, OFF at (20, 10) only in the second
    t = np.array([10_000, 50_000, 110_000, 150_000, 210_000, 250_000, 299_999])
    ev = np.zeros(len(t), dtype=hh.EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t, 5, 5, 1
    ev["x"][3], ev["y"][3], ev["p"][3] = 20, 10, -1
    rec = hh.Recording(events=ev, sensor_size=hh.SensorSize(30, 40))
    src = write_recording(rec, tmp_path / "r.h5")
    rc = main(["view", str(src), "--out", str(tmp_path / "c.mp4"), "--fps", "10", "--height", "60", "--still",
               str(tmp_path / "mid.png"), "--json", "--no-progress", "--playback-fps", "5"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    res = json.loads(out.out)
    assert res["frames"] == 3 and res["panels"] == ["events"] and res["t_last_us"] == 310_000  # from the first event
    frames, meta = _decode(tmp_path / "c.mp4")
    assert len(frames) == 3 and abs(meta["fps"] - 5) < 0.01
    still = np.asarray(Image.open(tmp_path / "mid.png"))  # frame 2: [110 ms, 210 ms)
    assert still.shape == (LABEL_HEIGHT + 60 + BAR_HEIGHT, 80, 3)
    ev_panel = still[LABEL_HEIGHT:LABEL_HEIGHT + 60]
    assert tuple(ev_panel[11, 11]) == ON_COLOUR and tuple(ev_panel[21, 41]) == OFF_COLOUR  # x2 scale
    assert tuple(ev_panel[40, 60]) == BACKGROUND
    assert np.abs(frames[1].astype(int) - still.astype(int)).mean() < 8  # the MP4 holds the same picture
    # the time bar fills with time
    fill = [int((f[-4, :, 0] > 150).sum()) for f in frames]
    assert fill[0] < fill[1] < fill[2]


def test_view_on_ecd_with_reconstruction(tmp_path, capsys, shared_data):
    import json

    from hybridhdr.cli import main
    ecd = shared_data("ecd_slider_depth")
    assert main(["reconstruct", str(ecd), "--method", "direct", "--fps", "100", "--out", str(tmp_path / "rec"),
                 "--no-progress"]) == 0
    capsys.readouterr()
    rc = main(["view", str(ecd), "--recon", str(tmp_path / "rec"), "--fps", "100", "--out", str(tmp_path / "v.mp4"),
               "--json", "--no-progress"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    res = json.loads(out.out)
    assert res["panels"] == ["events", "frames", "reconstruction"] and res["frames"] == 18
    assert res["t_last_us"] <= 174_156 + 10_000  # stops with the events, not the frames (3.33 s)
    frames, _ = _decode(tmp_path / "v.mp4")
    assert len(frames) == 18 and frames[9].shape[1] == 3 * 480
    # --until last runs to the last frame; an empty window is an error naming the span
    rc = main(["view", str(ecd), "--out", str(tmp_path / "w.mp4"), "--start", "10s", "--no-progress"])
    assert rc == 1 and "3.33382 s" in capsys.readouterr().err and not (tmp_path / "w.mp4").exists()


def test_recon_panel_linear_like_the_frame_unless_hdr():
    from hybridhdr.formats.images import LOG_MAP_RATIO, apply_display_map
    from hybridhdr.view import recon_display_map
    rng = np.random.default_rng(0)
    # an ordinary scene in frame-linear units (code / 255), with a dark tail (the ECD slider's AKF output)
    codes = rng.integers(20, 122, (4, 30, 40)).astype(np.float64)
    recon = codes / 255.0
    recon[:, :2] = 0.002
    m = recon_display_map(recon)
    assert m == {"mode": "linear", "hi": 1.0, "gamma": 1.0}
    u8 = apply_display_map(recon[0], m)
    # equal intensities look alike in both panels: the frame panel shows code/255 of the dtype range
    np.testing.assert_array_equal(u8[2:], codes[0][2:].astype(np.uint8))
    # the preview log map would have lifted the same picture (washed out): mean code much higher
    log_u8, _ = tone_map(recon[0])
    assert log_u8[2:].mean() > u8[2:].mean() + 60
    # gamma-encoded frames: the linear map applies their transfer
    mg = recon_display_map(recon, gamma=2.2)
    assert apply_display_map(np.array([[0.5 ** 2.2]]), mg)[0, 0] == 128
    # brighter than the frame's clip level: the 99.5th percentile is the white point
    bright = codes / 255.0 * 3
    m2 = recon_display_map(bright)
    assert m2["mode"] == "linear" and m2["hi"] == pytest.approx(np.percentile(bright, 99.5))
    # an HDR video (a disc 1000x brighter, beyond the frame's clip level) keeps the log map
    hdr = np.full((2, 20, 20), 0.05)
    hdr[:, 5:15, 5:15] = 50.0
    m3 = recon_display_map(hdr)
    assert 50.0 > LOG_MAP_RATIO * 0.05 and m3["mode"] == "log"
    # NaN black, +inf white in both maps
    for mm in (m, m3):
        out = apply_display_map(np.array([[np.nan, np.inf, -np.inf]]), mm)
        assert out.tolist() == [[0, 255, 0]]
