#!/usr/bin/env bash
# The checks that need a GPU, in one run: the kernel tests on CUDA (against the PyTorch reference and the serial
# sort; the parallel sort is Taichi's radix sort), the same refinements recorded on CUDA and on the CPU and
# compared, the throughput table on CUDA (queries per second, render-times per query, sequential and in lockstep
# batches; the 7-Scenes-shaped job with 64 queries so that a batch of 32 fills; the densified room's batches
# with their working sets' union up to the whole map, at most 2x and none: backend.DEFAULT_UNION_LIMIT), the
# derivative pass with and without pixel masks, the tile lists binned by ellipse and by box, and the map-scale
# table.
# Usage (the package installed with its test extras, ../shared/data beside the repository):
#   bash benchmarks/gpu_check.sh [OUT_DIR]        (about 5 minutes on an H100)
set -u -o pipefail
out=${1:-gpu_check_out}
mkdir -p "$out"
cd "$(dirname "$0")/.." || exit 2
status=0
HGSLOC_ARCH=cuda python -m pytest -q -p no:cacheprovider tests/test_tile_sort.py tests/test_render.py \
    tests/test_pose_grad.py tests/test_working_set.py tests/test_lod.py tests/test_lockstep.py tests/test_layout.py 2>&1 \
    | tee "$out/tests_cuda.log" || status=1
grep -q " passed" "$out/tests_cuda.log" && ! grep -qE " (failed|error)" "$out/tests_cuda.log" || status=1
HGSLOC_ARCH=cuda python benchmarks/backends.py --out "$out/cuda.json" || status=1
HGSLOC_ARCH=cpu python benchmarks/backends.py --out "$out/cpu.json" || status=1
python benchmarks/backends.py --compare "$out/cpu.json" "$out/cuda.json" --md "$out/compare.md" || status=1
HGSLOC_ARCH=cuda python benchmarks/throughput.py --shaped-queries 64 --out "$out/throughput_cuda.md" || status=1
HGSLOC_ARCH=cuda python benchmarks/throughput.py --cases room_x20 --union-limit 1 \
    --out "$out/throughput_cuda_no_union.md" || status=1
HGSLOC_ARCH=cuda python benchmarks/throughput.py --cases room_x20 --union-limit 2 \
    --out "$out/throughput_cuda_union2.md" || status=1
HGSLOC_ARCH=cuda python benchmarks/derivative_pass.py --out "$out/derivative_pass_cuda.md" || status=1
HGSLOC_ARCH=cuda python benchmarks/tile_lists.py --out "$out/tile_lists_cuda.md" || status=1
HGSLOC_ARCH=cuda python benchmarks/map_scale.py --paths "whole map, search" "working set, gradient first" \
    --out "$out/map_scale_cuda.md" || status=1
exit $status
