"""API behaviour: parameter validation and TOML, profiles, streaming, outputs, CLI."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from hybridhdr import Recording, make_events
from hybridhdr.camera import CameraProfile, default_profile
from hybridhdr.reconstruct import AKFParams, CFParams, HighPassParams, reconstruct, reconstruct_iter

from .conftest import ideal_recording


@pytest.mark.parametrize("cls, kw, exc", [
    (AKFParams, dict(process_noise_per_s=-1.0), ValueError),
    (AKFParams, dict(noise_model="matlab"), ValueError),
    (AKFParams, dict(initial_covariance=0.0), ValueError),
    (AKFParams, dict(refractory_period_us=1.5), ValueError),
    (AKFParams, dict(contrast_threshold="0.1"), TypeError),
    (AKFParams, dict(bias_correction=1), TypeError),
    (AKFParams, dict(covariance_interpolation="cubic"), ValueError),
    (AKFParams, dict(intensity_offset=float("nan")), ValueError),
    (CFParams, dict(cutoff_hz=-0.5), ValueError),
    (CFParams, dict(adaptive_low=0.9, adaptive_high=0.1), ValueError),
    (HighPassParams, dict(contrast_threshold_on=0.0), ValueError),
])
def test_bad_params(cls, kw, exc):
    with pytest.raises(exc, match=list(kw)[0]):
        cls(**kw)


def test_params_positional_and_frozen():
    with pytest.raises(TypeError):
        AKFParams(0.1)  # keyword-only
    p = AKFParams()
    with pytest.raises(Exception):
        p.contrast_threshold = 0.2


def test_params_toml_and_presets(tmp_path):
    f = tmp_path / "run.toml"
    f.write_text('[akf]\ncontrast_threshold = 0.2\nnoise_model = "reference_code"\n[cf]\ncutoff_hz = 2.0\n')
    assert AKFParams.from_toml(f) == AKFParams(contrast_threshold=0.2, noise_model="reference_code")
    assert CFParams.from_toml(f).alpha_rad_per_s == pytest.approx(4 * np.pi)
    with pytest.raises(ValueError, match="unknown AKFParams"):
        AKFParams.from_dict({"sigma_p": 1})
    r = AKFParams.reference_code()
    assert (r.process_noise_per_s, r.initial_covariance, r.intensity_offset) == (5e-3, 0.09, 1.0)
    p = AKFParams.paper()
    assert (p.process_noise_per_s, p.intensity_offset, p.saturation, p.frame_update, p.event_interpolation) == \
        (5e-4, 1.0, "value", "continuous", False)
    assert AKFParams.default() == AKFParams()
    assert (AKFParams().saturation, AKFParams().intensity_offset) == ("bound", 1e-3)
    assert AKFParams(contrast_threshold_on=0.2).c_on == 0.2 and AKFParams(contrast_threshold_on=0.2).c_off == 0.1


def test_bad_calls():
    rec, _ = ideal_recording()
    with pytest.raises(ValueError, match="unknown method"):
        reconstruct(rec, "no_such_method")
    with pytest.raises(ValueError, match="strictly increasing"):
        reconstruct(rec, "akf", times_us=[30_000, 20_000])
    with pytest.raises(ValueError, match="before the filter can start"):
        reconstruct(rec, "akf", times_us=[10])
    with pytest.raises(ValueError, match="exactly one"):
        reconstruct(rec, "akf", times_us=[10_000], fps=30)
    with pytest.raises(ValueError, match="mode"):
        reconstruct(rec, "akf", mode="online")
    with pytest.raises(ValueError, match="fps"):
        reconstruct(rec, "akf", fps=-3)
    with pytest.raises(TypeError, match="params"):
        reconstruct(rec, "akf", CFParams())
    with pytest.raises(ValueError, match="needs frames"):
        reconstruct(Recording(rec.events, rec.sensor_size), "akf")
    with pytest.raises(ValueError, match="causal"):
        reconstruct(rec, "frames_linear", mode="causal")


def test_highpass_events_only():
    rec, _ = ideal_recording()
    v = reconstruct(Recording(rec.events, rec.sensor_size), "hpf", fps=100)
    assert len(v) > 10 and np.isfinite(v.frames).all() and v.frames.dtype == np.float32


def test_profile_roundtrip_and_errors(tmp_path):
    p = default_profile(8)
    assert p.max_code == 255 and p.weighting.max() == 1.0
    path = p.save(tmp_path / "cam.json")
    q = CameraProfile.load(path)
    np.testing.assert_array_equal(q.weighting, p.weighting)
    assert q.frame_precision_scale == 7e5
    d = json.loads(path.read_text())
    d["format"] = "other"
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="format"):
        CameraProfile.load(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="weighting"):
        CameraProfile(weighting=[0.5, 2.0])
    with pytest.raises(ValueError, match="non-decreasing"):
        CameraProfile(weighting=[1.0, 1.0, 1.0], inverse_crf=[0.0, 0.7, 0.5])
    # eq. 6: R̄ = 1/(scale max(f_w, floor))
    assert p.variance(np.array([0, 128]))[1] == pytest.approx(1 / 7e5)
    assert p.variance(np.array([0]))[0] == pytest.approx(1 / (7e5 * 0.09))
    v1 = reconstruct(ideal_recording()[0], "akf", profile=path)
    v2 = reconstruct(ideal_recording()[0], "akf")
    np.testing.assert_array_equal(v1.frames, v2.frames)


def test_streaming_from_container_equals_in_memory(tmp_path):
    container = pytest.importorskip("hybridhdr.formats.container")
    rec, _ = ideal_recording()
    path = tmp_path / "rec.h5"
    container.write_recording(rec, path)
    a = reconstruct(rec, "akf", fps=300)
    with container.RecordingFile(path) as f:
        b = list(reconstruct_iter(f, "akf", fps=300, chunk_events=97))
    assert [t for t, _ in b] == a.t_us.tolist()
    np.testing.assert_array_equal(np.stack([im for _, im in b]), a.frames)
    c = reconstruct(str(path), "akf", fps=300, chunk_events=1000)
    np.testing.assert_array_equal(c.frames, a.frames)


def test_window_and_empty_events():
    rec, _ = ideal_recording()
    v = reconstruct(rec, "akf", fps=100, t_start_us=50_000, t_end_us=100_000)
    assert v.t_us[0] == 50_000 and v.t_us[-1] < 100_000
    rec0 = Recording(make_events(np.zeros(0, np.int64), [], [], []), rec.sensor_size, rec.frames)
    v0 = reconstruct(rec0, "akf")
    assert len(v0) == len(rec.frames) and np.isfinite(v0.frames).all()


def test_outputs(tmp_path):
    from hybridhdr.formats.images import read_exr, tone_map, write_exr_sequence, write_png_previews
    v = reconstruct(ideal_recording()[0], "akf", fps=100)
    paths = write_exr_sequence(v, tmp_path / "exr")
    np.testing.assert_array_equal(read_exr(paths[3]), v.frames[3])
    lines = (tmp_path / "exr" / "timestamps.txt").read_text().splitlines()
    assert lines[4].split() == [str(v.t_us[3]), "frame_000003.exr"]
    assert len(write_png_previews(v, tmp_path / "png", every=5)) == (len(v) + 4) // 5
    img, (lo, hi) = tone_map(np.array([[1e-3, 1.0], [10.0, 100.0]]), low_percentile=0, high_percentile=100)
    assert img.dtype == np.uint8 and img.min() == 0 and img.max() == 255
    assert not list((tmp_path / "exr").glob("*.partial*"))


def test_cli_run(tmp_path):
    from hybridhdr.formats.container import write_recording
    from hybridhdr.reconstruct import cli
    rec, _ = ideal_recording()
    write_recording(rec, tmp_path / "rec.h5")
    ap = argparse.ArgumentParser()
    cli.add_parser(ap.add_subparsers())
    toml = tmp_path / "run.toml"
    toml.write_text("[akf]\nprocess_noise_per_s = 1e-3\n")
    args = ap.parse_args(["reconstruct", str(tmp_path / "rec.h5"), "--out", str(tmp_path / "out"), "--fps", "50",
                          "--config", str(toml), "--set", "refractory_period_us=5000", "--png", "--no-progress"])
    assert args.func(args) == 0
    info = json.loads((tmp_path / "out" / "run.json").read_text())
    assert info["params"]["process_noise_per_s"] == 1e-3 and info["params"]["refractory_period_us"] == 5000
    assert (tmp_path / "out" / "timestamps.txt").exists()
    bad = ap.parse_args(["reconstruct", str(tmp_path / "rec.h5"), "--out", str(tmp_path / "o2"),
                         "--set", "nonsense=1", "--no-progress"])
    assert bad.func(bad) == 2


def test_prefetch_order_errors_and_early_stop():
    """The reader thread keeps order, re-raises the reader's error in the consumer, and stops
    (and is joined) when the consumer stops early."""
    import threading

    from hybridhdr._util.prefetch import Prefetcher as _prefetch

    assert list(_prefetch(iter(range(50)))) == list(range(50))

    def failing():
        yield 1
        yield 2
        raise OSError("disk gone")

    got = []
    with pytest.raises(OSError, match="disk gone"):
        for v in _prefetch(failing()):
            got.append(v)
    assert got == [1, 2]

    produced = []

    def endless():
        i = 0
        while True:
            produced.append(i)
            yield i
            i += 1

    it = _prefetch(endless(), depth=2)
    assert [next(it) for _ in range(5)] == [0, 1, 2, 3, 4]
    it.close()
    assert not any(th.name == "hybridhdr-prefetch" for th in threading.enumerate())
    assert len(produced) <= 5 + 2 + 1  # at most depth items (plus one in flight) read ahead


def _chunked(rec, n):
    ev = rec.events
    for i in range(0, len(ev), n):
        c = ev[i:i + n]
        yield c["t"].copy(), c["x"].copy(), c["y"].copy(), c["p"].copy()


def test_streaming_event_arrays_equal_in_memory_arrays():
    """Windows, counts and chunks of the background-filled arrays equal the in-memory ones."""
    from hybridhdr.reconstruct.event_arrays import EventArrays, StreamingEventArrays
    rec, _ = ideal_recording()
    shape = (rec.sensor_size.height, rec.sensor_size.width)
    ref = EventArrays.from_structured(rec.events, shape)
    s = StreamingEventArrays(_chunked(rec, 97), shape, len(rec.events))
    t0, t1 = int(ref.t[0]), int(ref.t[-1])
    for a, b in ((t0, t0 + 1000), (t0 + 33_333, t0 + 90_001), (t1 - 10, t1 + 5), (t0 - 100, t1 + 100)):
        assert s.window(a, b) == ref.window(a, b)
        for u, v in zip(s.counts(a, b), ref.counts(a, b)):
            np.testing.assert_array_equal(u, v)
    assert len(s) == len(ref)
    got = list(s.chunks(1000))
    assert max(len(c[0]) for c in got) == 1000
    for i in range(4):
        np.testing.assert_array_equal(np.concatenate([c[i] for c in got]), getattr(ref, "txyp"[i]))
    s.close()


def test_streaming_event_arrays_errors_and_stop():
    import threading

    from hybridhdr.reconstruct.event_arrays import StreamingEventArrays
    rec, _ = ideal_recording()
    shape = (rec.sensor_size.height, rec.sensor_size.width)
    n = len(rec.events)
    chunks = list(_chunked(rec, 500))
    # time order broken across a chunk boundary: raised to the reader of a later window
    bad = [chunks[0], (chunks[1][0] - 10**6,) + chunks[1][1:]] + chunks[2:]
    s = StreamingEventArrays(iter(bad), shape, n)
    with pytest.raises(ValueError, match="non-decreasing; index 500"):
        s.window(0, int(rec.events["t"][-1]))
    # more events than declared
    s = StreamingEventArrays(iter(chunks), shape, n - 1)
    with pytest.raises(ValueError, match=f"declared {n - 1} events"):
        len(s)
    # coordinates outside the sensor
    s = StreamingEventArrays(iter(chunks), (shape[0], 3), n)
    with pytest.raises(ValueError, match="exceed the sensor size"):
        len(s)
    # fewer than declared (a file that ends early): the arrays end there
    s = StreamingEventArrays(iter(chunks[:3]), shape, n)
    assert len(s) == 1500 and s.t.shape == (1500,) and s.window(0, 10**12) == (0, 1500)

    def endless():
        c = chunks[0]
        k = 0
        while True:  # time-ordered forever
            yield (c[0] * 0 + k,) + c[1:]
            k += 1
    s = StreamingEventArrays(endless(), shape, 10**9)
    assert s.window(0, 3) == (0, 1500)  # waits only until an event at t >= 3 is in
    s.close()
    assert not any(th.name == "hybridhdr-events" and th.is_alive() for th in threading.enumerate())


def test_augmented_streaming_equals_read_all_first(tmp_path):
    """Frame augmentation on a source that declares its event count (read in the background)
    gives the result of a source that does not (all events read first), bit for bit."""
    rec, _ = ideal_recording()

    class Undeclared:  # a reader without n_events
        sensor_size = rec.sensor_size

        def read_frames(self):
            return rec.frames

        def iter_chunks(self, n):
            for i in range(0, len(rec.events), n):
                yield rec.events[i:i + n]

    # augmentation is opt-in (AugmentParams().enabled is False): ask for it
    # the same thresholds and span for both (a reader without a path or a time range can be neither
    # self-calibrated nor cut at its last event)
    kw = dict(fps=300, chunk_events=101, augment=True, thresholds="input", t_end_us=int(rec.events["t"][-1]) + 1)
    a = reconstruct(Undeclared(), "akf", **kw)
    b = reconstruct(rec, "akf", **kw)
    assert "augmentation" in a.info and "augmentation" in b.info  # both ran the frame augmentation
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.t_us, b.t_us)
