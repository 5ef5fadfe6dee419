#!/usr/bin/env bash
# Every device figure of the scaling work in one run, on a host with an NVIDIA GPU and many cores
# (python3 with numba, numba-cuda, h5py preinstalled; no network; hybridhdr not installed; run from
# the repo root of a fresh checkout):
#     OUT=/some/folder bash benchmarks/device_run.sh
# Steps, each with its own timeout so that one failure or stall does not lose the others (each
# prints its duration):
#   1. env.txt: versions, nvidia-smi, CPU count
#   2. cuda_checks.jsonl: GPU vs CPU agreement (tests/reconstruct/cuda_checks.py --real)
#   3. gpu.json (+ gpu_stderr.txt): benchmarks/gpu.py at 1280x720: resident forward and two-sided
#      AKF, the walk's cost breakdown against simplified walks, transfers (pinned vs pageable),
#      end to end from a file against the decoder's rate, reconstruct on the GPU
#   4. cpu_scaling.json (+ cpu_scaling_stderr.txt): benchmarks/akf.py --workers 1,2,4,8,16 at
#      1280x720, forward and two-sided, both CPU engines side by side
#   5. summary.txt: the headline figures pulled from the JSON files
# Timeouts (seconds): CHECKS_TIMEOUT_S (80), GPU_TIMEOUT_S (220), CPU_TIMEOUT_S (160): at most 7.7 min.
set -u
OUT=${OUT:-$(mktemp -d -t hybridhdr-device-XXXXXX)}
echo "logs in $OUT"
mkdir -p "$OUT"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
if ls .whl/*.whl >/dev/null 2>&1; then  # carried wheels, if any (installed into a private folder)
  site=$(mktemp -d -t hybridhdr-site-XXXXXX)
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
    && export PYTHONPATH=$PWD:$site
fi
T0=$(date +%s)
{
  date -u; nvidia-smi; uname -a; nproc; uptime
  python3 -c "import sys, numpy, numba; print(sys.version); print('numpy', numpy.__version__, 'numba', numba.__version__)"
  python3 -m pip list 2>/dev/null | grep -i -E "^(numba|numba-cuda|cupy|torch|llvmlite|h5py|scipy|isal|tqdm) "
  python3 -c "from hybridhdr.reconstruct.request import Device; print(Device.resolve('auto').line)"
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"

echo "== 1/3 GPU vs CPU agreement (tests/reconstruct/cuda_checks.py --real)"
timeout "${CHECKS_TIMEOUT_S:-80}" python3 tests/reconstruct/cuda_checks.py --real \
  2> "$OUT/cuda_checks_stderr.txt" > "$OUT/cuda_checks.jsonl"
echo "(exit $?)"
python3 - "$OUT/cuda_checks.jsonl" <<'PY' || true
import json, sys
d = [json.loads(s) for s in open(sys.argv[1]) if s.startswith("{")]
bad = [x.get("check") for x in d if not x.get("ok") and "skip" not in x]
print("agreement: skipped" if d and "skip" in d[0] else f"agreement: {len(d) - len(bad)} of {len(d)} checks ok",
      ("FAILED: " + ", ".join(map(str, bad))) if bad else "")
for x in d:
    if not x.get("ok") and "error" in x:
        print(x["check"], x["error"])
PY
tail -n 3 "$OUT/cuda_checks_stderr.txt"
T1=$(date +%s); echo "(agreement: $((T1 - T0)) s since start)"

echo "== 2/3 benchmarks/gpu.py (1280x720, 10 M events)"
timeout "${GPU_TIMEOUT_S:-220}" python3 benchmarks/gpu.py --skip agreement,firenet --no-cpu --reps 2 \
  --hd-events 10000000 2> "$OUT/gpu_stderr.txt" > "$OUT/gpu.json"
echo "(exit $?)"
grep -v -i warning "$OUT/gpu_stderr.txt" | tail -n 40
T2=$(date +%s); echo "(gpu.py: $((T2 - T1)) s)"

echo "== 3/3 benchmarks/akf.py --workers 1,2,4,8,16 (1280x720 forward and two-sided, both CPU engines)"
timeout "${CPU_TIMEOUT_S:-160}" python3 benchmarks/akf.py --workers 1,2,4,8,16 --rounds 2 \
  --cases forward_1280x720,two_sided_1280x720 --scaling-events 1000000,6000000 \
  2> "$OUT/cpu_scaling_stderr.txt" > "$OUT/cpu_scaling.json"
echo "(exit $?)"
grep -v -i warning "$OUT/cpu_scaling_stderr.txt" | tail -n 20
T3=$(date +%s); echo "(akf.py --workers: $((T3 - T2)) s)"

python3 - "$OUT" <<'PY' 2>&1 | tee "$OUT/summary.txt" || true
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
def last_json(p):
    try:
        lines = [s for s in p.read_text().splitlines() if s.startswith("{")]
        return json.loads(lines[-1]) if lines else {}
    except OSError:
        return {}
g = last_json(out / "gpu.json")
hd = g.get("hd", {})
print("device:", g.get("device"), "| errors:", g.get("errors"))
for k in ("akf_forward_resident", "akf_two_sided_resident", "transfer_pageable", "transfer_pinned",
          "walk_breakdown", "end_to_end_file", "akf_forward_reconstruct_gpu", "akf_two_sided_reconstruct_gpu"):
    print(k, json.dumps(hd.get(k)))
c = last_json(out / "cpu_scaling.json").get("scaling", {})
for name, d in c.get("cases", {}).items():
    print(name, d.get("engine"), "Mev/s", d.get("mev_s"), "speed-up", d.get("speedup"),
          "efficiency", d.get("efficiency"), "bit-identical", d.get("bit_identical"))
for name, d in c.get("engines_side_by_side", {}).items():
    print(name, "pixel/row-band", d.get("pixel_over_row_band"), "same frames", d.get("identical_frames"))
PY
T4=$(date +%s); echo "(total $((T4 - T0)) s)"
