#!/bin/bash
# jaxpbr on an NVIDIA GPU, in one pass: correctness against CPU renders, timings, the default test suite.
#
#   bash examples/gpu_check.sh [CPU_REFERENCE_DIR] [SECONDS]
#
# Needs a Python whose jax has a CUDA backend (jax[cuda12] or jax[cuda13]) with jaxpbr's dependencies
# installed (`pip install -e '.[test]'`). CPU_REFERENCE_DIR (optional) holds demo_cpu.exr and
# gltf_cpu.exr, rendered on a CPU with
#     jaxpbr render --width 640 --height 360 --hdr --output DIR/demo_cpu.png
#     python -c "from jaxpbr.rendering.demo import write_demo_glb; write_demo_glb('DIR/grid50k.glb', triangles=50000)"
#     jaxpbr render DIR/grid50k.glb --environment procedural:sky --width 640 --height 360 --hdr --output DIR/gltf_cpu.png
# and the same renders made here are compared with them. Results go to $OUT (default ./gpu_check_out); the
# whole run is held under SECONDS (default 540): the test suite gets what the benchmarks leave.
set -o pipefail
REF=${1:-}
BUDGET=${2:-540}
OUT=${OUT:-gpu_check_out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
CACHE=$(mktemp -d)
export XDG_CACHE_HOME="$CACHE"  # empty caches: the first demo run is cold
left() { echo $((BUDGET - SECONDS)); }
step() { echo; echo "=== $1 (t=${SECONDS}s)"; }

step "device"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import jax, jaxlib, numpy; print('jax', jax.__version__, 'numpy', numpy.__version__, jax.devices())" || exit 1
nproc

step "demo: whole-process wall time, 1280x720 (cold, then warm on the caches it filled)"
for i in 1 2 3; do
  /usr/bin/time -f "run $i: %e s wall, %M KB peak" jaxpbr render --output "$CACHE/demo$i.png" 2>&1 | grep -E "run $i|render "
done

if [ -n "$REF" ]; then
  step "GPU against CPU renders (640x360 linear HDR)"
  timeout 60 jaxpbr render --width 640 --height 360 --hdr --output "$OUT/demo_gpu.png" | tail -1
  timeout 120 jaxpbr render "$REF/grid50k.glb" --environment procedural:sky --width 640 --height 360 --hdr \
    --output "$OUT/gltf_gpu.png" | tail -1
  python3 - "$REF" "$OUT" <<'EOF'
import sys
import numpy as np
from jaxpbr.io import image
ref, out = sys.argv[1:]
for name in ("demo", "gltf"):
    try:
        a = np.asarray(image.read(f"{out}/{name}_gpu.exr"), np.float64)
        b = np.asarray(image.read(f"{ref}/{name}_cpu.exr"), np.float64)
    except Exception as e:  # noqa: BLE001
        print(name, "not compared:", e)
        continue
    rel = np.abs(a - b) / np.maximum(np.abs(b), 1e-2)
    print(f"{name}: finite {np.isfinite(a).all()}, relative difference mean {rel.mean():.2e} p99 "
          f"{np.quantile(rel, 0.99):.2e} max {rel.max():.2e}; pixels over 1e-3: {np.mean(rel.max(-1) > 1e-3):.4%}")
EOF
fi

step "float64 exactness checks that differ on CUDA (exposure stops, shipped sheen LUT)"
timeout 90 python3 -m pytest -q -p no:randomly tests/test_color.py -k "exposure" 2>&1 | tail -3

step "asset cache: 1 M-triangle glTF rendered twice (the second process loads the built BVH)"
python3 -c "from jaxpbr.rendering.demo import write_demo_glb; write_demo_glb('$CACHE/grid1m.glb')"
for i in 1 2; do
  /usr/bin/time -f "asset run $i: %e s wall, %M KB peak" timeout 120 jaxpbr render "$CACHE/grid1m.glb" \
    --environment procedural:sky --width 640 --height 360 --output "$CACHE/g$i.png" 2>&1 | grep -E "asset run|render "
done

step "visibility: JAX BVH on the GPU, 1920x1080 primary and shadow rays"
timeout 120 python3 examples/bench_visibility.py --subdiv 6 8 --backends jax --shadow --repeats 5 2>&1 | tail -12

step "jaxpbr bench render (G-buffer: JAX vs NumPy; materials batch)"
timeout 90 jaxpbr bench render --width 1920 --height 1080 2>&1 | tail -25

step "jaxpbr bench render --gltf (1 M triangles, 1920x1080, 4 lights + IBL)"
timeout 170 jaxpbr bench render --gltf --cold-runs 1 2>&1 | tail -40

step "default test suite (what is left of ${BUDGET}s)"
T=$(( $(left) - 15 ))
if [ "$T" -gt 30 ]; then
  timeout -s INT "$T" python3 -m pytest -q -n 12 --maxprocesses 12 --durations 15 -p no:randomly 2>&1 \
    | tee "$OUT/suite.txt" | grep -vE "^\.|^s|PASSED" | tail -60
else
  echo "no time left for the suite"
fi
step "done"
