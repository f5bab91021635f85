# Sourced by benchmarks/gpu_check.sh: on a lent device machine (no network, ../shared not sent: .gpu/ there and
# no Taichi), unpack the Python packages its image lacks and the data from .gpu/ (made here by
# benchmarks/gpu_pack.sh, carried there) and install this package; elsewhere nothing. Sets PY: PYTHON, else
# python3 (the device's holds PyTorch).
PY=${PYTHON:-python3}
if [ -d .gpu ] && ! "$PY" -c "import taichi" >/dev/null 2>&1; then
  if [ ! -d /tmp/gpu_site/taichi ]; then  # a warm machine keeps it from an earlier run
    mkdir -p /tmp/gpu_site && tar -C /tmp/gpu_site -xJf .gpu/site.tar.xz \
      || { echo "gpu_setup: unpacking .gpu/site.tar.xz failed" >&2; exit 2; }
  fi
  export PYTHONPATH=/tmp/gpu_site${PYTHONPATH:+:$PYTHONPATH}
  "$PY" -m pip install -q --no-index --no-deps --no-build-isolation -e . \
    || { echo "gpu_setup: installing the package failed" >&2; exit 2; }
  if [ ! -d ../shared/data ]; then
    mkdir -p ../shared/data && tar -C ../shared/data -xJf .gpu/data.tar.xz \
      || { echo "gpu_setup: unpacking .gpu/data.tar.xz into ../shared/data failed" >&2; exit 2; }
  fi
fi
