#!/usr/bin/env bash
# `make test-portable`: the suite as another x86-64 machine runs it (issue 32). Floats differ
# in their last bits between CPUs (numpy's SIMD kernels, the BLAS, MuJoCo, Open3D), so a
# test's verdict must not ride on them. Runs the default suite three times:
#   1. numpy's AVX512 dispatch off (NPY_DISABLE_CPU_FEATURES: the features of this machine
#      above AVX2, so numpy picks the kernels of an AVX2-only machine), 1 thread per library;
#   2. the same with 2 threads per library (OpenMP: Open3D; OpenBLAS; MKL);
#   3. as `make test` runs it (all of numpy's kernels, 1 thread per library).
# and fails unless all three pass (the same set: all of it).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${VENV:-.venv}/bin/python
# numpy's dispatch targets above AVX2 (X86_V3) that this machine runs (numpy 2.4: X86_V4,
# AVX512_ICL, AVX512_SPR); switched off, numpy runs the kernels an AVX2-only CPU runs
avx512=$("$PY" -c '
from numpy._core._multiarray_umath import __cpu_dispatch__ as d, __cpu_features__ as f
print(" ".join(k for k in d if f.get(k) and (k.startswith("AVX512") or k == "X86_V4")))')
echo "[test-portable] numpy AVX512 features switched off: ${avx512:-none (this CPU has none)}"
run() {
  local label=$1
  shift
  echo "[test-portable] == $label"
  env "$@" "$PY" -m pytest -q -n auto --maxprocesses 4 --dist loadfile --no-loadscope-reorder -p no:cacheprovider
}
for threads in 1 2; do
  run "AVX512 off, $threads thread(s)" NPY_DISABLE_CPU_FEATURES="$avx512" \
    OMP_NUM_THREADS=$threads OPENBLAS_NUM_THREADS=$threads MKL_NUM_THREADS=$threads
done
run "as make test runs it" OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
echo "[test-portable] the same set passed in all three runs"
