#!/usr/bin/env bash
# The library the way a user gets it: install the build into a temporary prefix, check that the
# shared library exports the C API alone, build the README's examples against the installed CMake
# package (shared and static) and the C one with pkg-config, and check that every program's label
# map equals what the installed `pillarseg infer` writes for the same scan and checkpoint, on the
# CPU and on the emulated CUDA backend; and that the Python module installed beside the library
# gives the same labels.
# Usage: tests/install_test.sh SOURCE_DIR BUILD_DIR WORK_DIR
set -euo pipefail
src=$1 build=$2 work=$3
rm -rf "$work"
mkdir -p "$work"
prefix=$work/prefix
say() { echo "install_test: $*"; }

cmake --install "$build" --prefix "$prefix" > "$work/install.log"
lib=$(ls "$prefix"/lib*/libpillarseg.so)
libdir=$(dirname "$lib")
for f in "$prefix/include/pillarseg/pillarseg.h" "$prefix/include/pillarseg/pillarseg.hpp" \
         "$libdir/libpillarseg.a" "$libdir/cmake/pillarseg/pillarsegConfig.cmake" \
         "$libdir/pkgconfig/pillarseg.pc" "$prefix/bin/pillarseg"; do
  [[ -e $f ]] || { say "missing after install: $f"; exit 1; }
done
others=$(nm -D --defined-only "$lib" | awk '{print $3}' | grep -v '^pillarseg_' || true)
if [[ -n $others ]]; then
  say "libpillarseg.so exports more than the C API:"
  echo "$others" | head -20
  exit 1
fi
say "libpillarseg.so exports $(nm -D --defined-only "$lib" | wc -l) symbols, all pillarseg_*"

# A small data set and model, made with the installed command line.
bin=$prefix/bin/pillarseg
"$bin" simulate --out "$work/data" --sequences 1 --scans 2 --seed 4 --points-per-scan 30000 > /dev/null
cat > "$work/tiny.yaml" <<'YAML'
grid: {x: [-20.0, 20.0], y: [-10.0, 10.0], z: [-2.5, 1.5], cell: 0.4, voxel_z: 0.2}
model: {max_points_per_pillar: 8, pillar_channels: 8, occupancy: 2d, occupancy_channels: 4, base_width: 8, depth: 2}
train: {epochs: 1, batch_size: 2, seed: 1, sequences: [0]}
eval: {sequences: [0]}
YAML
"$bin" --threads 2 train --data "$work/data" --config "$work/tiny.yaml" --out "$work/run" > /dev/null 2>&1
weights=$work/run/checkpoint.safetensors
scan=$work/data/sequences/00/velodyne/000001.bin

# A sanitized build (make asan) installs a sanitized libpillarseg.a: programs linking it need the
# sanitizers' runtimes, as they would in a user's sanitized build.
link_flags=()
if grep -q '^PILLARSEG_SANITIZE:BOOL=ON' "$build/CMakeCache.txt" 2> /dev/null; then
  link_flags=(-fsanitize=address,undefined)
fi
cmake -S "$src/examples" -B "$work/examples" -DCMAKE_PREFIX_PATH="$prefix" -DCMAKE_BUILD_TYPE=Release \
      -DCMAKE_EXE_LINKER_FLAGS="${link_flags[*]}" > "$work/examples.log"
cmake --build "$work/examples" >> "$work/examples.log"
cmake -S "$src/examples" -B "$work/examples-static" -DCMAKE_PREFIX_PATH="$prefix" -DCMAKE_BUILD_TYPE=Release \
      -DCMAKE_EXE_LINKER_FLAGS="${link_flags[*]}" -DPILLARSEG_EXAMPLES_STATIC=ON > "$work/examples-static.log"
cmake --build "$work/examples-static" >> "$work/examples-static.log"
PKG_CONFIG_PATH=$libdir/pkgconfig cc -O2 -o "$work/segment_scan_pkgconfig" "$src/examples/segment_scan.c" \
  $(PKG_CONFIG_PATH=$libdir/pkgconfig pkg-config --cflags --libs pillarseg) -Wl,-rpath,"$libdir" ${link_flags[@]+"${link_flags[@]}"}

for device in cpu emu; do
  "$bin" --threads 2 infer --weights "$weights" --scan "$scan" --out "$work/infer_$device" --device "$device" > /dev/null
  for program in examples/segment_scan_c examples/segment_scan_cpp examples-static/segment_scan_c \
                 segment_scan_pkgconfig; do
    out=$work/$(echo "$program" | tr '/' '_')_$device.u8
    "$work/$program" "$weights" "$scan" "$out" "$device" > "$out.log"
    if ! cmp -s "$out" "$work/infer_$device.u8"; then
      say "$program on $device: its labels differ from pillarseg infer's"
      cat "$out.log"
      exit 1
    fi
  done
  say "$device: the C, C++, static and pkg-config programs give pillarseg infer's labels ($(head -1 "$out.log"))"
done

# The Python module installed beside the library: it finds that library by itself (no
# PILLARSEG_LIBRARY) and gives pillarseg infer's labels. It needs numpy (Debian's python3-numpy).
python=
for candidate in python3 /usr/bin/python3; do
  if "$candidate" -c 'import numpy' 2> /dev/null; then python=$candidate; break; fi
done
if [[ -z $python ]]; then
  say "python: no python3 with numpy here: the installed Python module is not checked"
  exit 0
fi
package=$(ls -d "$prefix"/lib*/python3*/*-packages/pillarseg)
env -u PILLARSEG_LIBRARY PYTHONPATH="$(dirname "$package")" "$python" - "$weights" "$scan" "$work/infer_cpu.u8" \
    "$prefix" <<'PY'
import os, sys
import numpy as np
import pillarseg
weights, scan, expected, prefix = sys.argv[1:]
library = os.path.realpath(pillarseg.library_path)
if not library.startswith(os.path.realpath(prefix) + os.sep):
    sys.exit(f"install_test: the installed module loaded {library}, not the library in {prefix}")
with pillarseg.Segmenter(weights, threads=2) as segmenter:
    labels = segmenter.segment(pillarseg.read_points(scan))
if not np.array_equal(labels.ravel(), np.fromfile(expected, dtype=np.uint8)):
    sys.exit("install_test: the installed Python module's labels differ from pillarseg infer's")
print(f"install_test: python: {pillarseg.__file__} on {library} gives pillarseg infer's labels")
PY
