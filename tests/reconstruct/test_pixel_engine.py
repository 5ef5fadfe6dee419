"""The pixel-parallel CPU engine of the AKF equals the row-band engine bit for bit.

Every comparison is exact (``np.array_equal`` on the float64 state or the float32 images): both
engines apply the same per-event function (``_kernels.akf_event_step``) to the same events of each
pixel in the same order with the same t*, so any difference is a bug, not rounding.
"""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.camera import default_profile
from hybridhdr.reconstruct import AKFParams, FrameMeasurements, reconstruct
from hybridhdr.reconstruct import _engine as E
from hybridhdr.reconstruct import _pixel_engine as PX

from .test_parallel import _frames, _stream, _StepMeasurements

def _run(engine_cls, n_workers, h, w, ev, frames, params, measurements=None, cuts=(), thresholds=None, t_origin=0):
    """Drive ``engine_cls`` through the events, cut into windows at ``cuts`` and the frame switches;
    outputs (state) at a few times."""
    m = measurements or FrameMeasurements(frames, (h, w), default_profile(), intensity_offset=params.intensity_offset)
    eng = engine_cls((h, w), m, params, n_workers)
    if thresholds is not None:
        eng.set_thresholds(*thresholds)
    t, x, y, p = ev
    clock = E.OutputClock(times_us=t_origin + np.array([60_000, 120_000, 190_000]))
    chunks = []
    bounds = [0, *sorted(cuts), len(t)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        chunks.append((t[a:b], x[a:b], y[a:b], p[a:b]))
    outs = [(to, img.copy()) for to, img in E.drive(eng, chunks, clock)]
    S = eng.S.copy()
    n = eng.n_events
    eng.close()
    return outs, S, n


@pytest.fixture
def threaded_windows(monkeypatch):
    """Every window of these small streams through the workers (not the calling thread alone)."""
    monkeypatch.setattr(PX, "PARALLEL_MIN_EVENTS", 0)


#: the ways a worker gets and filters its events: its band selected from the whole window, in
#: stream order; the window split once by rows (histogram and scatter), in stream order; the same
#: split, grouped by pixel and walked
PATHS = ("select", "split", "pixel")


def _set_path(monkeypatch, path):
    monkeypatch.setattr(PX, "BLOCK_ORDER", "pixel" if path == "pixel" else "stream")
    monkeypatch.setattr(PX, "SELECT_MAX_WORKERS", 1 << 20 if path == "select" else 0)


@pytest.mark.parametrize("n_workers", [1, 2, 3, 5])
@pytest.mark.parametrize("variant", ["paper", "reference", "la_step", "thresholds", "exposures"])
@pytest.mark.parametrize("path", PATHS)
def test_pixel_engine_bit_identical(n_workers, variant, path, threaded_windows, monkeypatch):
    _set_path(monkeypatch, path)
    h, w = 13, 17
    ev = _stream(6_000, h, w, seed=n_workers, t0=1_000, boundary_rows=(0, 5, 6, 12))
    ev[1][::7] = 3  # a busy column: long groups, many active neighbours
    frames = _frames(h, w, [1_000, 50_000, 100_000, 150_000])
    if variant == "exposures":  # unequal exposures: every frame through the per-pixel measurement path
        from hybridhdr.model import Frames
        frames = Frames(frames.images, frames.t_start_us, frames.t_start_us + np.array([800, 2_000, 500, 1_000]),
                        encoding=frames.encoding)
        assert FrameMeasurements(frames, (h, w), default_profile(), intensity_offset=0.1).segment_codes(0) is None
    params = AKFParams(noise_model="reference_code" if variant == "reference" else "paper")
    thr = None
    if variant == "thresholds":
        rng = np.random.default_rng(4)
        thr = (rng.uniform(0.08, 0.2, (h, w)), rng.uniform(0.08, 0.2, (h, w)))

    def meas():
        if variant != "la_step":
            return None
        return _StepMeasurements(FrameMeasurements(frames, (h, w), default_profile(),
                                                   intensity_offset=params.intensity_offset))
    ref = _run(E.AKFEngine, 1, h, w, ev, frames, params, meas(), thresholds=thr)
    cuts = (1_000, 1_001, 2_500, 4_000)  # windows of one event, chunk ends in the middle of a window
    got = _run(PX.PixelAKFEngine, n_workers, h, w, ev, frames, params, meas(), cuts=cuts, thresholds=thr)
    assert got[2] == ref[2]
    np.testing.assert_array_equal(got[1], ref[1])
    for (ta, a), (tb, b) in zip(got[0], ref[0]):
        assert ta == tb
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("path", PATHS)
def test_more_workers_than_rows_and_empty_windows(path, threaded_windows, monkeypatch):
    _set_path(monkeypatch, path)
    h, w = 3, 40
    ev = _stream(2_000, h, w, seed=9, t0=1_000)
    frames = _frames(h, w, [1_000, 90_000])
    ref = _run(E.AKFEngine, 1, h, w, ev, frames, AKFParams())
    got = _run(PX.PixelAKFEngine, 8, h, w, ev, frames, AKFParams(), cuts=(0, 10, 10, 1_999))
    np.testing.assert_array_equal(got[1], ref[1])


@pytest.mark.parametrize("n_workers", [1, 3])
@pytest.mark.parametrize("path", PATHS)
def test_int32_last_event_times_widen_to_int64(n_workers, path, threaded_windows, monkeypatch):
    """The int32 last-event times (relative to the start) become int64 absolute ones past int32's
    reach (about 35 minutes; shortened here to 150 ms), ghost-row copies included: the serial
    filter's bits either way."""
    _set_path(monkeypatch, path)
    h, w = 13, 17
    t0 = (1 << 33) + 11
    ev = _stream(8_000, h, w, seed=12, t0=t0, span=300_000, boundary_rows=(0, 5, 6, 12))
    frames = _frames(h, w, [t0 - 11, t0 + 100_000, t0 + 200_000, t0 + 299_000])
    params = AKFParams(frame_precision_scale=1e3)
    ref = _run(E.AKFEngine, 1, h, w, ev, frames, params, t_origin=t0)
    dtypes = []
    fit = PX.PixelAKFEngine._te_fit

    def spy(self, a, b):
        fit(self, a, b)
        dtypes.append((self.te_px.dtype, self.ghost.dtype))
    monkeypatch.setattr(PX.PixelAKFEngine, "_te_fit", spy)
    monkeypatch.setattr(E, "TE32_MAX", 150_000)
    got = _run(PX.PixelAKFEngine, n_workers, h, w, ev, frames, params, cuts=(2_000, 5_000), t_origin=t0)
    assert dtypes[0] == (np.int32, np.int32) and dtypes[-1] == (np.int64, np.int64), dtypes
    np.testing.assert_array_equal(got[1], ref[1])
    for (ta, a), (tb, b) in zip(got[0], ref[0]):
        assert ta == tb
        np.testing.assert_array_equal(a, b)


def test_small_windows_in_the_calling_thread():
    """Windows below PARALLEL_MIN_EVENTS are filtered without the workers: the same bits."""
    h, w = 13, 17
    ev = _stream(6_000, h, w, seed=3, t0=1_000, boundary_rows=(0, 5, 6, 12))
    frames = _frames(h, w, [1_000, 50_000, 100_000, 150_000])
    ref = _run(E.AKFEngine, 1, h, w, ev, frames, AKFParams())
    got = _run(PX.PixelAKFEngine, 3, h, w, ev, frames, AKFParams(), cuts=(1_000, 2_500))
    np.testing.assert_array_equal(got[1], ref[1])
    for (ta, a), (tb, b) in zip(got[0], ref[0]):
        assert ta == tb
        np.testing.assert_array_equal(a, b)


def test_plan_bands():
    """Bands of about equal events, each at least one row; each list holds its rows' and its two
    ghost rows' events, worker by worker."""
    rng = np.random.default_rng(0)
    hist = rng.integers(0, 5, (3, 20))
    hist[:, 12] += 200  # one busy row
    edges, bor, eor, start, pos = PX.plan_bands(hist, 4)
    assert edges[0] == 0 and edges[-1] == 20 and np.all(np.diff(edges) >= 1)
    for v in range(4):
        lo, hi = edges[v], edges[v + 1]
        assert np.all(bor[lo:hi] == v)
        rows = slice(max(lo - 1, 0), min(hi + 1, 20))
        assert start[v + 1] - start[v] == hist[:, rows].sum()
        for wk in range(3):
            assert pos[wk, v] == start[v] + hist[:wk, rows].sum()
    # ghost flags: the first row of band v > 0 is read by band v - 1, the last row of band v < 3 by v + 1
    assert [int(r) for r in np.flatnonzero(eor & 1)] == [int(e) for e in edges[1:4]]
    assert [int(r) for r in np.flatnonzero(eor & 2)] == [int(e) - 1 for e in edges[1:4]]
    # the busy row sits alone or nearly: no band holds more than the busy row plus a share of the rest
    own = [hist[:, edges[v]:edges[v + 1]].sum() for v in range(4)]
    assert max(own) <= hist[:, 12].sum() + hist.sum() // 4
    # more bands than rows: one row each
    edges, *_ = PX.plan_bands(np.ones((2, 3), np.int64), 8)
    assert list(edges) == [0, 1, 2, 3]


def test_choice_and_report():
    m = FrameMeasurements(_frames(4, 5, [0, 10]), (4, 5), default_profile(), intensity_offset=0.01)
    assert PX.cpu_akf_engine((4, 5), m, AKFParams(), 1).kind == "row-band"
    assert PX.cpu_akf_engine((4, 5), m, AKFParams(), PX.PIXEL_MIN_WORKERS).kind == "pixel-parallel"
    assert PX.cpu_akf_engine((4, 5), m, AKFParams(), 1, engine="pixel-parallel").kind == "pixel-parallel"
    with pytest.raises(ValueError, match="engine must be one of"):
        PX.cpu_akf_engine((4, 5), m, AKFParams(), 1, engine="fast")
    k = PX.PIXEL_MIN_WORKERS
    assert PX.engine_line("akf", "cpu", k) == f"; cpu engine: pixel-parallel ({k} workers)"
    assert PX.engine_line("akf", "cpu", k - 1) == f"; cpu engine: row-band ({k - 1} worker{'s' if k > 2 else ''})"
    assert PX.engine_line("akf", "cpu", 1, "offline") == "; cpu engine: row-band (1 worker)"
    assert PX.engine_line("akf", "cpu", 2 * k, "offline") == (f"; cpu engine: pixel-parallel ({k} workers), "
                                                              f"pixel-parallel ({k} workers) (backward and forward "
                                                              f"pass at once)")
    assert PX.engine_line("cf", "cpu", 2) == "" and PX.engine_line("akf", "cuda", 2) == ""


def _calibrated(c_on, c_off, intensity_offset, frame_time_offset_us):
    """The camera model the default self-calibration finds for a recording (rounded), stated:
    both engines run on a calibrated model (thresholds, log offset and frame time offset away
    from the defaults) without estimating it again in every run, which costs far more than the
    runs compared. The engines' agreement does not depend on which model; the estimation has
    its own tests (tests/calibrate)."""
    return {"params": {"contrast_threshold_on": c_on, "contrast_threshold_off": c_off,
                       "intensity_offset": intensity_offset},
            "frame_time_offset_us": frame_time_offset_us}


EDGE_SWEEP_MODEL = _calibrated(0.0989, 0.0993, 0.002, 1250)
COLOUR_MODEL = _calibrated(0.0940, 0.0962, 0.004, 3750)
ECD_MODEL = _calibrated(0.0824, 0.0427, 2.048, 7753)


def _reconstruct_both(rec, monkeypatch, **kw):
    """``reconstruct`` with every CPU AKF engine row-band, then pixel-parallel (same workers)."""
    out = []
    for engine in ("row-band", "pixel-parallel"):
        monkeypatch.setattr(PX, "ENGINE", engine)
        v = reconstruct(rec, "akf", **kw)
        assert "self_calibration" not in v.info  # the stated model, not a new estimate
        out.append(np.asarray(v.frames))
    return out


@pytest.fixture(scope="module")
def edge_sweep():
    """The edge sweep recording, built once (seconds of simulation) for the six comparisons below,
    which only read it."""
    from hybridhdr.simulate.procedural import edge_sweep_recording
    return edge_sweep_recording(0)[0]


@pytest.mark.parametrize("mode", ["offline", "forward", "causal"])
@pytest.mark.parametrize("n_workers", [1, 2])
def test_edge_sweep_bit_identical(monkeypatch, edge_sweep, mode, n_workers):
    rec = edge_sweep
    a, b = _reconstruct_both(rec, monkeypatch, mode=mode, n_workers=n_workers, fps=200, **EDGE_SWEEP_MODEL)
    assert np.array_equal(a.view(np.uint32), b.view(np.uint32))


@pytest.fixture(scope="module")
def colour_edge_sweep():
    """The colour edge sweep recording, built once for the two comparisons below (read only)."""
    from hybridhdr.simulate.procedural import colour_edge_sweep_recording
    return colour_edge_sweep_recording(0, cfa="RGGB", band_limited=True, duration_us=300_000)[0]


@pytest.mark.parametrize("mode", ["offline", "forward"])
def test_colour_bit_identical(monkeypatch, colour_edge_sweep, mode):
    rec = colour_edge_sweep
    a, b = _reconstruct_both(rec, monkeypatch, mode=mode, n_workers=2, **COLOUR_MODEL)
    assert np.array_equal(a.view(np.uint32), b.view(np.uint32))


@pytest.mark.parametrize("mode", ["offline", "causal"])
def test_ecd_slider_depth_bit_identical(monkeypatch, shared_data, mode):
    import hybridhdr
    rec = hybridhdr.read(shared_data("ecd_slider_depth"))
    t0 = int(rec.frames.t_start_us[0])
    a, b = _reconstruct_both(rec, monkeypatch, mode=mode, n_workers=2, t_end_us=t0 + 800_000, augment=False,
                             chunk_events=50_000, **ECD_MODEL)
    assert np.array_equal(a.view(np.uint32), b.view(np.uint32))
