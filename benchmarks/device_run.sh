#!/usr/bin/env bash
# The GPU checks in one run, on a host with an NVIDIA GPU (python3 with numba,
# numba-cuda and torch preinstalled; no network; hybridhdr not installed). From the repo root:
#     bash benchmarks/device_run.sh [benchmarks/gpu.py's options]
# e.g. a profiled run that skips the agreement case (under 4 min on an H200):
#     bash benchmarks/device_run.sh --profile --no-cpu --skip agreement
# Logs go to $OUT (default: a new temporary folder, printed): env.txt (versions, nvidia-smi),
# cuda_checks.jsonl (GPU vs CPU agreement, one JSON line per check), gpu.json (benchmarks/gpu.py's
# JSON) and gpu_stderr.txt (its progress lines: every figure and phase table, even if it is cut
# short). Each step has a timeout (CHECKS_TIMEOUT_S, GPU_TIMEOUT_S) and prints its duration.
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
{
  date -u; nvidia-smi; uname -a
  python3 -c "import sys, numpy, numba; print(sys.version); print('numpy', numpy.__version__, 'numba', numba.__version__)"
  python3 -m pip list 2>/dev/null | grep -i -E "^(numba|numba-cuda|cupy|torch|llvmlite|h5py|scipy|isal|openexr|mitsuba|tqdm) "
  python3 -c "from hybridhdr.reconstruct.request import Device; print(Device.resolve('auto').line)"
} 2>&1 | tee "$OUT/env.txt"
T0=$(date +%s)
echo "== GPU vs CPU agreement (tests/reconstruct/cuda_checks.py --real, as test_cuda.py runs it)"
timeout "${CHECKS_TIMEOUT_S:-100}" python3 tests/reconstruct/cuda_checks.py --real 2> "$OUT/cuda_checks_stderr.txt" | tee "$OUT/cuda_checks.jsonl"
python3 -c "
import json, sys
d = [json.loads(s) for s in open(sys.argv[1]) if s.startswith('{')]
bad = [x.get('check') for x in d if not x.get('ok') and 'skip' not in x]
print('agreement: skipped' if d and 'skip' in d[0] else f'agreement: {len(d) - len(bad)} of {len(d)} checks ok',
      ('FAILED: ' + ', '.join(map(str, bad))) if bad else '')
" "$OUT/cuda_checks.jsonl"
tail -n 5 "$OUT/cuda_checks_stderr.txt"
T1=$(date +%s); echo "(agreement checks: $((T1 - T0)) s)"
echo "== benchmarks/gpu.py $*"
timeout "${GPU_TIMEOUT_S:-150}" python3 benchmarks/gpu.py "$@" 2> "$OUT/gpu_stderr.txt" | tee "$OUT/gpu.json"
grep -v -i warning "$OUT/gpu_stderr.txt" | tail -n 150
T2=$(date +%s); echo "(gpu.py: $((T2 - T1)) s; total $((T2 - T0)) s)"
