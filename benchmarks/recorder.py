"""Soak test of the capture recorder: a synthetic 20 Mev/s stream for 60 s (10 s with --quick), then
a DV network stream on loopback beside a file replay of the same events (``dv_*`` and ``replay_*``).

Usage: ``python benchmarks/recorder.py [--quick]``. Progress goes to stderr; the last stdout line
is ONE JSON object.

The source (:class:`hybridhdr.capture.sources.SyntheticEventSource`) releases 10 ms chunks in
real time, like a camera driver, and the recorder runs with ``on_full="drop"`` — what it does for a
live camera — so a writer that cannot keep up shows up as counted drops, never as a slower source.
After the recording is finished (journal replayed into an uncompressed container) every event is
read back and compared, event by event, with what the generator produced (chunk ``k`` is a fixed
chunk shifted by ``k`` × 10 ms, so a lost, duplicated or reordered chunk is caught): ``lost`` is
generated − read back, ``sequence_ok`` says every chunk in the file is complete and exact, and
``all_loss_counted`` that the missing chunks are exactly the ones the recorder counted as dropped.

On a shared machine the figures depend on the CPU the process gets: ``cpu_cores_used_while_recording``
reports it, and ``cpu_ms_per_mev`` (source + recorder CPU time per million events, from the
max-rate phase) gives the rate one free core would sustain.

Memory: resident set size sampled every 50 ms from ``/proc/self/status`` (VmRSS) during the
recording, plus the peak (VmHWM) over the whole run. A second phase measures the recorder's
maximum sustained rate with a source that is never paced (``pace="fast"``, blocking queue).

Output files go to a temporary folder (``--dir``, default under ``/tmp``) deleted at the end.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def _loadavg():
    try:
        return [float(v) for v in Path("/proc/loadavg").read_text().split()[:3]]
    except (OSError, ValueError):
        return None


class RssSampler(threading.Thread):
    def __init__(self, period_s=0.05):
        super().__init__(daemon=True)
        self.period_s, self.max_kb, self._stop_ev = period_s, 0, threading.Event()

    def run(self):
        while not self._stop_ev.is_set():
            self.max_kb = max(self.max_kb, _status_kb("VmRSS"))
            self._stop_ev.wait(self.period_s)

    def stop(self):
        self._stop_ev.set()
        self.join()
        return self.max_kb / 1024


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def soak(folder: Path, rate: float, duration_s: float, chunk_us: int, queue_chunks: int, flush_s: float,
         sensor=(720, 1280)):
    from tqdm import tqdm

    from hybridhdr.capture.recorder import Recorder
    from hybridhdr.capture.sources import SyntheticEventSource
    from hybridhdr.formats.container import RecordingFile

    class LiveSynthetic(SyntheticEventSource):
        can_backpressure = False  # behave like a camera: the recorder drops instead of blocking

    src = LiveSynthetic(rate, sensor_size=sensor, chunk_us=chunk_us, duration_s=duration_s, pace="realtime",
                        seed=0)
    out = folder / "soak.h5"
    rss = RssSampler()
    rss.start()
    rec = Recorder(out, src, queue_chunks=queue_chunks, flush_interval_s=flush_s, compression=None)
    load0 = _loadavg()
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    rec.start()
    with tqdm(total=round(duration_s), unit="s", desc="soak recording", file=sys.stderr) as bar:
        done = 0
        while True:
            rec.wait(1.0)
            el = min(int(time.perf_counter() - t0), round(duration_s))
            bar.update(el - done)
            done = el
            bar.set_postfix(mev=f"{rec.stats.events_written / 1e6:.0f}", drops=rec.stats.events_dropped,
                            q=rec._q.qsize())
            if not rec._threads[0].is_alive():
                break
    rec.stop()
    rec_wall = time.perf_counter() - t0
    cpu_rec = time.process_time() - cpu0
    rss_rec_mb = rss.stop()
    load1 = _loadavg()
    journal_mb = rec.stats.journal_bytes / 1e6
    log(f"recorded {rec.stats.events_written:,} events in {rec_wall:.1f} s; finishing (journal {journal_mb:.0f} MB)")
    rec.progress = True
    stats = rec.finish()
    log(f"finished in {stats.finish_s:.1f} s; reading back")
    t = time.perf_counter()
    with RecordingFile(out) as f:
        size_mb = out.stat().st_size / 1e6
        with tqdm(total=f.n_events, unit="ev", unit_scale=True, desc="read back", file=sys.stderr) as bar:
            def blocks():
                for ev in f.iter_events(1 << 22):
                    bar.update(len(ev))
                    yield ev
            # raises if any chunk in the file is incomplete, duplicated, reordered or differs
            chk = src.check_stream(blocks())
    n = chk["events"]
    chunks_missing = src.chunks_emitted - chk["chunks_present"]
    readback_s = time.perf_counter() - t
    return {
        "target_rate_mev_s": rate / 1e6, "duration_s": duration_s, "chunk_us": chunk_us,
        "queue_chunks": queue_chunks, "flush_interval_s": flush_s,
        "events_generated": src.events_emitted, "events_written": stats.events_written,
        "events_read_back": n, "events_dropped": stats.events_dropped, "lost": src.events_emitted - n,
        "sequence_ok": True, "chunks_generated": src.chunks_emitted, "chunks_missing": chunks_missing,
        "chunks_dropped_counted": stats.event_chunks_dropped,
        "all_loss_counted": chunks_missing == stats.event_chunks_dropped
        and src.events_emitted - n == stats.events_dropped,
        "achieved_source_rate_mev_s": src.events_emitted / rec_wall / 1e6, "record_wall_s": rec_wall,
        "cpu_cores_used_while_recording": cpu_rec / rec_wall,
        "flushes": stats.flushes, "max_queue_depth": stats.max_queue_depth,
        "peak_rss_recording_mb": rss_rec_mb, "journal_mb": journal_mb,
        "journal_mb_per_s": journal_mb / rec_wall, "finish_s": stats.finish_s,
        "finish_mev_s": stats.events_written / stats.finish_s / 1e6 if stats.finish_s else None,
        "container_mb": size_mb, "readback_s": readback_s, "loadavg_before": load0, "loadavg_after": load1,
    }


def max_rate(folder: Path, duration_s: float, chunk_us: int, queue_chunks: int):
    """Events per second the recorder takes from an unpaced source (blocking queue)."""
    from hybridhdr.capture.recorder import Recorder
    from hybridhdr.capture.sources import SyntheticEventSource

    src = SyntheticEventSource(20e6, chunk_us=chunk_us, pace="fast", seed=1)
    rec = Recorder(folder / "max.h5", src, queue_chunks=queue_chunks, flush_interval_s=1.0, compression=None)
    cpu0 = time.process_time()
    rec.start()
    rec.wait(duration_s)
    rec.stop()
    cpu = time.process_time() - cpu0
    st = rec.stats
    rec._jw.close()
    ms_per_mev = 1e3 * cpu / (st.events_written / 1e6)
    return {"max_recording_rate_mev_s": st.events_written / st.duration_s / 1e6,
            "max_rate_events": st.events_written, "max_rate_wall_s": st.duration_s,
            "max_rate_cpu_cores_used": cpu / st.duration_s,
            # CPU cost of source + recorder per million events; 1000 / this = Mev/s on one free core
            "cpu_ms_per_mev": ms_per_mev, "rate_on_one_free_core_mev_s": 1e3 / ms_per_mev}


_DV_SERVER = """
import json, os, sys
from hybridhdr.capture.dv_backend import serve_recording
print(json.dumps(serve_recording(sys.argv[1], {"events": sys.argv[2]}, speed=None, wait_clients_s=120)), flush=True)
os._exit(0)
"""


def dv_stream(folder: Path, n_events: int, rate: float, chunk_us: int, queue_chunks: int):
    """A DV network stream on loopback (UNIX socket) into the recorder, beside a file replay of the same data.

    The events are the synthetic generator's (exactly checkable, chunk by chunk), written once into an
    AEDAT4 file (not timed). Phase "replay": :class:`ReplayEventSource` reads the file unpaced into the
    recorder (blocking queue). Phase "dv": a separate process serves the same file with dv-processing's
    ``NetworkWriter`` as fast as the socket takes it (``serve_recording(speed=None)``), and the recorder
    records it through :class:`DvCapture` (pump thread, bounded buffer): the sustained rate is events
    written over the time from the first batch received to the end of the stream, and every event the
    server sent and the file does not hold is a loss — compared with the recorder's and the pump's drop
    counts and the stream interruptions.
    """
    import os
    import subprocess

    import hybridhdr
    from hybridhdr.capture.dv_backend import DvCapture
    from hybridhdr.capture.recorder import Recorder
    from hybridhdr.capture.sources import ReplayEventSource, SyntheticEventSource
    from hybridhdr.formats.container import RecordingFile

    gen = SyntheticEventSource(rate, sensor_size=(260, 346), chunk_us=chunk_us, pace="fast", seed=2)
    n_chunks = max(1, n_events // gen.chunk_events)
    ev = np.concatenate([c.events for c, _ in zip(gen, range(n_chunks))])
    src_file = folder / "stream.aedat4"
    t = time.perf_counter()
    hybridhdr.write(hybridhdr.Recording(ev, hybridhdr.SensorSize(260, 346)), src_file, format="aedat4")
    log(f"wrote {len(ev):,} events to {src_file.name} in {time.perf_counter() - t:.1f} s")
    check = SyntheticEventSource(rate, sensor_size=(260, 346), chunk_us=chunk_us, pace="fast", seed=2)

    def verify(path):
        with RecordingFile(path) as f:
            return check.check_stream(f.iter_events(1 << 22))

    # replay phase
    rp = ReplayEventSource(src_file, pace="fast", chunk_us=chunk_us)
    rec = Recorder(folder / "replay.h5", rp, queue_chunks=queue_chunks, compression=None)
    rec.start()
    rec.wait()
    st = rec.finish()
    replay = {"replay_events": st.events_written, "replay_wall_s": st.duration_s,
              "replay_mev_s": st.events_written / st.duration_s / 1e6, "replay_events_dropped": st.events_dropped,
              "replay_check": verify(folder / "replay.h5")}
    log(f"replay: {replay['replay_mev_s']:.2f} Mev/s")

    # DV stream phase
    sock = folder / "events.sock"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    server = subprocess.Popen([sys.executable, "-c", _DV_SERVER, str(src_file), f"dv-unix://{sock}"],
                              stdout=subprocess.PIPE, text=True, env=env)
    try:
        while not sock.exists():
            if server.poll() is not None:
                raise RuntimeError("the DV server ended before opening its socket")
            time.sleep(0.02)
        cap = DvCapture([f"dv-unix://{sock}"], reconnect_timeout_s=0.5, buffer_items=4096)
        es = cap.event_source()
        first = {}

        def on_flush(d):
            if d["events_written"] and "t" not in first:
                first["t"] = time.perf_counter()
        rec = Recorder(folder / "dv.h5", es, queue_chunks=queue_chunks, compression=None, flush_interval_s=0.05,
                       on_flush=on_flush)
        t0 = time.perf_counter()
        rec.start()
        served = json.loads(server.stdout.readline())
        rec.wait(120)
        t_end = time.perf_counter()
        st = rec.finish()
    finally:
        if server.poll() is None:
            server.kill()
        server.communicate()
    chk = verify(folder / "dv.h5")
    c = st.source_counters.get("events", {})
    wall = t_end - t0
    lost = served["events"] - chk["events"]
    return {**replay, "dv_events_served": served["events"], "dv_events_written": st.events_written,
            "dv_events_lost": lost, "dv_recorder_events_dropped": st.events_dropped,
            "dv_buffer_events_dropped": c.get("events_dropped_in_buffer"),
            "dv_stream_interruptions": c.get("interruptions"), "dv_stream_restarts": c.get("restarts"),
            "dv_check": chk, "dv_wall_s": wall,
            # the stream ends with the reconnection window (0.5 s) the source waits before it gives up
            "dv_mev_s": st.events_written / max(wall - 0.5, 1e-9) / 1e6,
            "dv_all_loss_counted": lost == (st.events_dropped + (c.get("events_dropped_in_buffer") or 0))
            or bool(c.get("interruptions", 0) > c.get("ended", 0)),
            "dv_over_replay": (st.events_written / max(wall - 0.5, 1e-9)) / (replay["replay_mev_s"] * 1e6)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="10 s soak instead of 60 s")
    ap.add_argument("--rate-ev-per-s", type=float, default=20e6, help="source event rate")
    ap.add_argument("--duration-s", type=float, default=None, help="soak length (default 60, quick 10)")
    ap.add_argument("--chunk-us", type=int, default=10_000, help="source chunk length (µs)")
    ap.add_argument("--queue-chunks", type=int, default=64, help="recorder queue capacity (chunks)")
    ap.add_argument("--flush-interval-s", type=float, default=1.0, help="journal flush period")
    ap.add_argument("--max-rate-s", type=float, default=None, help="length of the max-rate phase (0 = skip)")
    ap.add_argument("--dir", type=Path, default=None, help="parent of the temporary output folder")
    ap.add_argument("--dv-events", type=int, default=None,
                    help="events of the DV-stream phase (default 20 M, quick 1 M; 0 = skip)")
    args = ap.parse_args(argv)
    dur = args.duration_s if args.duration_s is not None else (10.0 if args.quick else 60.0)
    mr = args.max_rate_s if args.max_rate_s is not None else (3.0 if args.quick else 10.0)
    folder = Path(tempfile.mkdtemp(prefix="hybridhdr_soak_", dir=args.dir))
    free_gb = shutil.disk_usage(folder).free / 1e9
    log(f"soak: {args.rate_ev_per_s / 1e6:.1f} Mev/s for {dur:.0f} s into {folder} ({free_gb:.0f} GB free); "
        f"load {_loadavg()}")
    try:
        res = soak(folder, args.rate_ev_per_s, dur, args.chunk_us, args.queue_chunks, args.flush_interval_s)
        (folder / "soak.h5").unlink()
        if mr > 0:
            log(f"max-rate phase: unpaced source for {mr:.0f} s")
            res.update(max_rate(folder, mr, args.chunk_us, args.queue_chunks))
        nd = args.dv_events if args.dv_events is not None else (1_000_000 if args.quick else 20_000_000)
        if nd > 0:
            try:
                import dv_processing  # noqa: F401
            except ImportError:
                log("DV-stream phase skipped: dv-processing is not installed (pip install 'hybridhdr[dv]')")
                res["dv_skipped"] = "dv-processing is not installed"
            else:
                log(f"DV-stream phase: {nd:,} events over a UNIX socket, beside a file replay of the same data")
                res.update(dv_stream(folder, nd, 5e6, args.chunk_us, args.queue_chunks))
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    res["peak_rss_mb"] = _status_kb("VmHWM") / 1024
    res["disk_free_gb"] = free_gb
    res["cpus"] = len(__import__("os").sched_getaffinity(0))
    res["pass"] = bool(res["lost"] == 0 and res["events_dropped"] == 0 and res["sequence_ok"])
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
