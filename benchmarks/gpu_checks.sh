#!/usr/bin/env bash
# The GPU checks in one run, for a machine with a CUDA GPU (H100 or the
# like) and a Python whose torch sees it, with diffaccel, cheetah and gpsr
# installed (`make install TORCH=torch` then `pip install -e ".[bench]"`):
#   PY=.venv/bin/python OUT=gpu_results bash benchmarks/gpu_checks.sh
# Runs the CUDA tests, then the benchmarks on the GPU, each writing JSON into
# $OUT: per-step time, ATen ops and host syncs at 6 144 and 100 000 particles
# (limits 3 ms and 5 ms; the CUDA-graph default and --eager as the same-run
# baseline), tracking + images vs cheetah on the same GPU (>= 5x both methods)
# with a 10^7 x 20 fit check, whole-process reconstruct vs gpsr on the same GPU
# (>= 5x), and the 6D benchmark with diffaccel on the GPU (docs/gpu.md holds
# the figures measured on an H200). Not part of `make bench` (CPU machines).
set -u
here=$(cd "$(dirname "$0")" && pwd)
PY=${PY:-"$here/../.venv/bin/python"}
OUT=$(mkdir -p "${OUT:-gpu_results}" && cd "${OUT:-gpu_results}" && pwd)
"$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 'no CUDA device')" || exit 2
"$PY" -c "import torch; print(torch.__version__, torch.cuda.get_device_name())" | tee "$OUT/device.txt"
(cd "$here/.." && "$PY" -m pytest -q -p no:cacheprovider -k cuda tests) > "$OUT/tests.txt" 2>&1
echo "cuda tests: exit $? ($(tail -n 1 "$OUT/tests.txt"))"
cd "$here" || exit 2
for n in 6144 100000; do
  "$PY" reconstruction_step.py --device cuda --particles $n --json "$OUT/step_$n.json" > /dev/null
  "$PY" reconstruction_step.py --device cuda --particles $n --eager --json "$OUT/step_${n}_eager.json" > /dev/null
done
"$PY" tracking.py --device cuda --fit-n 10000000 > "$OUT/tracking.json"
"$PY" reconstruction_process.py --device cuda --repeats 2 --json "$OUT/process.json" > /dev/null
"$PY" reconstruction_6d.py --skip-gpsr --device cuda --threads 8 --out "$OUT/sixd.json" > /dev/null
"$PY" - "$OUT" <<'PYEOF'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
names = ("step_6144", "step_6144_eager", "step_100000", "step_100000_eager",
         "tracking", "process", "sixd")
for name in names:
    path = out / f"{name}.json"
    if not path.exists():
        print(name, "missing")
        continue
    d = json.loads(path.read_text().strip().splitlines()[-1])
    if name == "sixd":
        d = d["diffaccel"]
    keys = ("cuda_graph", "step_time_s", "host_syncs_per_step", "aten_ops_per_step",
            "ratio_vs_cheetah_kde", "ratio_vs_cheetah_cic", "fit", "ratio", "met",
            "wall_s", "meets_moments_and_images", "fails")
    print(name, {k: d[k] for k in keys if k in d})
PYEOF
