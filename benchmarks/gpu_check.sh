#!/usr/bin/env bash
# The checks that need a GPU, in one run, most important first, within a time budget (a lent device gives a
# command 10 minutes):
#   1. the kernel tests on CUDA (against the PyTorch reference and the serial sort; the parallel sort is Taichi's
#      radix sort; kernels/launch.py's fast path against Taichi's own launches);
#   2. the throughput table on CUDA (issue 33's goals: queries per second and render-times per query, sequential
#      and in lockstep batches; the 7-Scenes-shaped job with 64 queries so that a batch of 32 fills);
#   3. the 7-Scenes-shaped job in processes sharing the GPU (plain processes, and Ray workers where Ray is
#      installed): the host side of a query outlasts its kernels there;
#   4. the same refinements recorded on CUDA and on the CPU, compared (the same poses within 0.001 % of the depth);
#   5. the fast preset's throughput on CUDA (the 7-Scenes-shaped job, 64 queries: 30 queries per second?);
#   6. the tile lists binned by ellipse and by box (RasterConfig.tile_test's CUDA default);
#   7. the densified room's lockstep batches with their working sets' union up to 2x, and none
#      (backend.DEFAULT_UNION_LIMIT's CUDA default);
#   8. the derivative pass in its layouts: tiles, pixels with and without pixel masks (RasterConfig.blend's and
#      grad_masks' CUDA defaults);
#   9. the map-scale table.
# A step starts only while the budget (GPU_CHECK_BUDGET_S seconds, default 540) lasts, and is stopped at its end;
# OUT_DIR/steps.log lists each step's exit status and seconds ("skipped" past the budget).
# Exit status: 0 all passed, 1 a step failed, 3 none failed but some were skipped or stopped for time.
# Usage (the package installed with its test extras, ../shared/data beside the repository):
#   bash benchmarks/gpu_check.sh [OUT_DIR]
# On a lent device machine: run benchmarks/gpu_pack.sh here first and carry .gpu there (gpu_setup.sh installs the
# packages and unpacks the data from it); Ray is not packed (too large), so the Ray rows of step 3 are skipped.
set -u -o pipefail
out=${1:-gpu_check_out}
mkdir -p "$out"
cd "$(dirname "$0")/.." || exit 2
budget=${GPU_CHECK_BUDGET_S:-540}
start=$SECONDS  # the setup's unpacking counts against the budget too
. benchmarks/gpu_setup.sh  # sets PY
status=0
: > "$out/steps.log"

step() {  # step NAME COMMAND...: run COMMAND with the budget's remaining time, log its status and seconds
  local name=$1 left t0 rc
  shift
  left=$((budget - (SECONDS - start)))
  if [ "$left" -le 10 ]; then
    echo "$name skipped" | tee -a "$out/steps.log"
    [ "$status" -eq 0 ] && status=3
    return
  fi
  t0=$SECONDS
  timeout "$left" "$@"
  rc=$?
  echo "$name rc=$rc $((SECONDS - t0))s" | tee -a "$out/steps.log"
  if [ "$rc" -eq 124 ]; then
    [ "$status" -eq 0 ] && status=3
  elif [ "$rc" -ne 0 ]; then
    status=1
  fi
}

cuda_tests() {
  HGSLOC_ARCH=cuda "$PY" -m pytest -q -p no:cacheprovider tests/test_tile_sort.py tests/test_render.py \
      tests/test_pose_grad.py tests/test_working_set.py tests/test_lod.py tests/test_lockstep.py \
      tests/test_layout.py tests/test_launch.py tests/test_window.py 2>&1 | tee "$out/tests_cuda.log"
  grep -q " passed" "$out/tests_cuda.log" && ! grep -qE " (failed|error)" "$out/tests_cuda.log"
}

backends() {
  HGSLOC_ARCH=cuda "$PY" -m benchmarks.backends --out "$out/cuda.json" \
    && HGSLOC_ARCH=cpu "$PY" -m benchmarks.backends --out "$out/cpu.json" \
    && "$PY" -m benchmarks.backends --compare "$out/cpu.json" "$out/cuda.json" --md "$out/compare.md"
}

unions() {
  HGSLOC_ARCH=cuda "$PY" -m benchmarks.throughput --cases room_x20 --union-limit 1 --rounds 1 \
      --out "$out/throughput_cuda_no_union.md" \
    && HGSLOC_ARCH=cuda "$PY" -m benchmarks.throughput --cases room_x20 --union-limit 2 --rounds 1 \
      --out "$out/throughput_cuda_union2.md"
}

export -f cuda_tests backends unions
export out PY
step tests bash -c cuda_tests
step throughput env HGSLOC_ARCH=cuda "$PY" -m benchmarks.throughput --shaped-queries 64 --rounds 1 \
    --out "$out/throughput_cuda.md"
step scale env HGSLOC_ARCH=cuda "$PY" -m benchmarks.scale --queries 64 --processes 4 8 --workers 4 8 \
    --threads 2 --out "$out/scale_cuda.md"
step backends bash -c backends
step presets env HGSLOC_ARCH=cuda "$PY" -m benchmarks.throughput --cases 7scenes_shaped --shaped-queries 64 \
    --rounds 1 --config fast --out "$out/throughput_cuda_fast.md"
step tile_lists env HGSLOC_ARCH=cuda "$PY" -m benchmarks.tile_lists --out "$out/tile_lists_cuda.md"
step unions bash -c unions
step derivative_pass env HGSLOC_ARCH=cuda "$PY" -m benchmarks.derivative_pass --out "$out/derivative_pass_cuda.md"
step map_scale env HGSLOC_ARCH=cuda "$PY" -m benchmarks.map_scale --paths "whole map, search" \
    "working set, gradient first" --out "$out/map_scale_cuda.md"
exit $status
