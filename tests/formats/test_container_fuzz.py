"""Fuzz the container reader: 2,000 seeded mutations of a small valid file.

Each mutated file must either read as a valid recording (sorted events inside the sensor) or raise
FormatError (a ValueError). HDF5's C library runs in-process, so the loop runs in a child process:
a crash or hang there fails this test with the index of the input instead of killing pytest.
"""

import json
import subprocess
import sys
import textwrap

N_INPUTS = 2000

CHILD = textwrap.dedent(r'''
    import io, json, os, sys, tempfile
    import numpy as np
    import hybridhdr as hh
    from hybridhdr.formats.container import RecordingFile, write_recording
    from hybridhdr.errors import FormatError

    n_inputs = int(sys.argv[1])
    rng = np.random.default_rng(20261121)
    d = tempfile.mkdtemp()
    t = np.sort(rng.integers(0, 50_000, 300))
    rec = hh.Recording(hh.make_events(t, rng.integers(0, 16, 300), rng.integers(0, 12, 300),
                                      rng.choice([-1, 1], 300)), (12, 16),
                       hh.Frames(rng.integers(0, 255, (2, 12, 16), dtype=np.uint8), [0, 20_000], [500, 20_500]),
                       hh.make_triggers([5, 600], [0, 0], [1, -1]))
    src = os.path.join(d, "src.h5")
    write_recording(rec, src, compression=None)
    data = bytearray(open(src, "rb").read())
    stats = {"ok": 0, "format_error": 0}
    path = os.path.join(d, "m.h5")
    for i in range(n_inputs):
        m = bytearray(data)
        kind = i % 4
        if kind == 0:                      # bit flips
            for _ in range(int(rng.integers(1, 8))):
                j = int(rng.integers(0, len(m)))
                m[j] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:                    # overwrite a run of bytes
            j = int(rng.integers(0, len(m)))
            k = int(rng.integers(1, 64))
            m[j:j + k] = rng.bytes(min(k, len(m) - j))
        elif kind == 2:                    # truncate
            m = m[: int(rng.integers(0, len(m)))]
        else:                              # insert bytes
            j = int(rng.integers(0, len(m)))
            m[j:j] = rng.bytes(int(rng.integers(1, 32)))
        open(path, "wb").write(m)
        sys.stdout.write(f"{i}\n"); sys.stdout.flush()
        try:
            with RecordingFile(path) as r:
                got = r.read()
                chunks = [c.events for c in r.iter_chunks(97)]
            hh.validate_events(got.events, got.sensor_size)
            if chunks:
                assert np.array_equal(np.concatenate(chunks), got.events)
            stats["ok"] += 1
        except FormatError:
            stats["format_error"] += 1
    print(json.dumps(stats))
''')


def test_container_reader_survives_mutations():
    try:
        proc = subprocess.run([sys.executable, "-c", CHILD, str(N_INPUTS)], capture_output=True, text=True,
                              timeout=600)
    except subprocess.TimeoutExpired as e:
        last = (e.stdout or b"").decode(errors="replace").strip().splitlines()[-1:]
        raise AssertionError(f"container reader hung on mutated input {last}") from None
    lines = proc.stdout.strip().splitlines()
    assert proc.returncode == 0, (f"child failed (rc={proc.returncode}) after input {lines[-1:]}:\n"
                                  f"{proc.stderr[-3000:]}")
    stats = json.loads(lines[-1])
    assert stats["ok"] + stats["format_error"] == N_INPUTS
    assert stats["format_error"] > 0
