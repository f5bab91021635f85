#!/usr/bin/env bash
# Prepare .gpu/ for benchmarks/gpu_check.sh on a lent device machine, which reaches no network and receives the
# working tree without ../shared (64 MiB in all, the carried paths included):
#   .gpu/site.tar.xz   the Python packages its image lacks, installed for its Python (3.12, x86-64): taichi
#                      (without its C API library, 20 MB the Python package does not load), dill, plyfile, and
#                      gsplat 1.5.3's Python files (the tests' reference projection is its pure-PyTorch code; its
#                      wheel's CUDA sources are left out);
#   .gpu/data.tar.xz   what the checks read of ../shared/data, named file by file: the snow photos and maps, lego,
#                      the scenes, and the ACE, Marepo and pseudo ground truth pose files of 7-Scenes.
# gpu_setup.sh unpacks them there when it finds .gpu/ (carry [".gpu"], command "bash benchmarks/gpu_check.sh $OUT").
# Ray is not packed (its wheel alone is 72 MB): the Ray rows of gpu_check's scale step are skipped there.
# Usage (here, with pip's index reachable): bash benchmarks/gpu_pack.sh
set -euo pipefail
cd "$(dirname "$0")/.."
data=../shared/data
[ -d "$data/snow" ] || { echo "gpu_pack: $data/snow not found" >&2; exit 2; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
pip_for_device=(python3 -m pip -q --disable-pip-version-check)
platforms=(--only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64
           --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
"${pip_for_device[@]}" install --no-deps "${platforms[@]}" --target "$tmp/site" "taichi==1.7.4" "dill>=0.3" \
    "plyfile>=1.0"
rm -rf "$tmp/site/taichi/_lib/c_api" "$tmp/site/taichi/examples" "$tmp/site/bin"
"${pip_for_device[@]}" download --no-deps --only-binary=:all: -d "$tmp" "gsplat==1.5.3"
python3 -m zipfile -e "$tmp"/gsplat-1.5.3-*.whl "$tmp/gsplat_whl"
(cd "$tmp/gsplat_whl" && find gsplat -name '*.py' -not -path 'gsplat/cuda/csrc/*' -print0 \
   | xargs -0 -I{} install -D -m 0644 {} "$tmp/site/{}")
rm -rf .gpu && mkdir .gpu
tar -C "$tmp/site" -cJf .gpu/site.tar.xz .
poses=()
for d in "$data"/poses/7scenes/*/; do
  for f in ace.txt marepo.txt pgt_sfm_test.txt; do poses+=("poses/7scenes/$(basename "$d")/$f"); done
done
snow=(snow/camera.json snow/gt.txt snow/queries snow/snow.ply snow/snow_sharp.ply)
tar -C "$data" -cJf .gpu/data.tar.xz "${snow[@]}" lego scenes "${poses[@]}"
tree_bytes=$(git ls-files -z | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1)
pack_bytes=$(du -cb .gpu | tail -1 | cut -f1)
limit=$((64 * 1024 * 1024))
echo "gpu_pack: .gpu $pack_bytes bytes + working tree $tree_bytes of the device's $limit"
[ $((pack_bytes + tree_bytes)) -le "$limit" ] || { echo "gpu_pack: over the device's limit" >&2; exit 1; }
