#!/usr/bin/env bash
# The GPU check in one call (DESIGN.md section 6): everything a bare CUDA machine needs to run the
# GPU tests, the compute sanitizer, the kernel benchmarks, the full-size bench and a short training
# comparison, packed into one directory with its run.sh (scripts/gpu_bundle_run.sh).
#
#   scripts/gpu_bundle.sh pack BUILD_DIR BUNDLE_DIR   binaries of a CUDA build, the shared libraries
#                                                     they need that such a machine lacks (ldd), the
#                                                     real scan from ../shared, configs, run.sh; and
#                                                     BUNDLE_DIR.tar.gz of it all (what travels)
#   scripts/gpu_bundle.sh check BUNDLE_DIR [MAX_MIB]  every library the binaries need is in the
#                                                     bundle, a CUDA library the machine has (driver,
#                                                     runtime, cuBLAS, cuDNN, NCCL) or the C/C++
#                                                     runtime; the size of BUNDLE_DIR.tar.gz (or of
#                                                     the directory, without one) is at most MAX_MIB
#                                                     (40; 0: no limit)
#
# `make gpu-bundle` builds build-gpu for GPU_ARCH (default 90) and packs build-gpu/bundle; `make
# test` packs and checks a bundle from the main build, whose binaries hold every default
# architecture (90 among them) and so are larger than one architecture's: there the size is
# reported, not limited.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
max_mib=40

# Libraries a bare CUDA machine has: the C/C++ runtime and the CUDA driver and libraries.
provided() {
  case "$1" in
    linux-vdso.so.*|ld-linux*.so.*|libc.so.*|libm.so.*|libdl.so.*|libpthread.so.*|librt.so.*) return 0 ;;
    libstdc++.so.*|libgcc_s.so.*) return 0 ;;
    libcuda.so.*|libcudart.so.*|libcublas.so.*|libcublasLt.so.*|libcudnn*.so.*|libnccl.so.*) return 0 ;;
  esac
  return 1
}

# The binaries of a bundle: the command line, every *_gpu test, the kernel benchmarks.
binaries_of() {
  local build=$1
  echo "$build/pillarseg"
  ls "$build"/tests/test_*_gpu
  ls "$build"/bench/bench_kernels_*
}

pack() {
  local build=$1 bundle=$2
  [[ -x $build/pillarseg ]] || { echo "gpu_bundle: no $build/pillarseg; build first"; exit 1; }
  ls "$build"/tests/test_*_gpu > /dev/null 2>&1 ||
    { echo "gpu_bundle: $build has no *_gpu tests (a build without nvcc?)"; exit 1; }
  rm -rf "$bundle"
  mkdir -p "$bundle/bin" "$bundle/lib/cxx" "$bundle/data" "$bundle/configs"
  for b in $(binaries_of "$build"); do
    cp "$b" "$bundle/bin/"
    strip --strip-unneeded "$bundle/bin/$(basename "$b")"
  done
  # The shared libraries they load that the machine lacks, in lib/; libstdc++ and libgcc_s, which
  # it has, perhaps older than these binaries need, in lib/cxx/ (run.sh uses them only then: they
  # need this machine's glibc or newer).
  for b in "$bundle"/bin/*; do
    ldd "$b" | awk '/=> \// {print $1, $3}'
  done | sort -u | while read -r name path; do
    if [[ $name == libstdc++.so.* || $name == libgcc_s.so.* ]]; then
      cp -L "$path" "$bundle/lib/cxx/$name"
    elif ! provided "$name"; then
      cp -L "$path" "$bundle/lib/$name"
    fi
  done
  local scan=$here/../shared/data/semantickitti/sequences/99
  if [[ -d $scan ]]; then
    mkdir -p "$bundle/data/sequences/99/velodyne" "$bundle/data/sequences/99/labels"
    cp "$scan/velodyne/000000.bin" "$bundle/data/sequences/99/velodyne/"
    cp "$scan/labels/000000.label" "$bundle/data/sequences/99/labels/"
  fi
  cp "$here"/configs/pillar_sparse.yaml "$here"/configs/pillar_2d_sparse.yaml \
     "$here"/configs/pillar_3d_sparse.yaml "$here"/configs/small_cpu.yaml "$bundle/configs/"
  cp "$here/scripts/gpu_bundle_run.sh" "$bundle/run.sh"
  chmod +x "$bundle/run.sh"
  git -C "$here" rev-parse --short HEAD > "$bundle/commit" 2>/dev/null || echo unknown > "$bundle/commit"
  # The compressed copy is what goes to the GPU machine (the binaries compress about 3:1).
  tar -C "$(dirname "$bundle")" -czf "$bundle.tar.gz.tmp" "$(basename "$bundle")"
  mv "$bundle.tar.gz.tmp" "$bundle.tar.gz"
  echo "gpu_bundle: packed $(du -sh "$bundle" | cut -f1) into $bundle, $(du -sh "$bundle.tar.gz" | cut -f1) as $bundle.tar.gz"
}

check() {
  local bundle=$1 limit=${2:-$max_mib} failed=0
  for b in "$bundle"/bin/*; do
    while read -r name path; do
      if [[ $path == "not" ]]; then
        if ! provided "$name" && [[ ! -e $bundle/lib/$name ]]; then
          echo "gpu_bundle check: $(basename "$b") needs $name, which is neither bundled nor a CUDA or C/C++ runtime library"
          failed=1
        fi
        continue
      fi
      if ! provided "$name" && [[ ! -e $bundle/lib/$name ]]; then
        echo "gpu_bundle check: $(basename "$b") needs $name ($path), which is not in the bundle"
        failed=1
      fi
    done < <(LD_LIBRARY_PATH=$bundle/lib ldd "$b" | awk '/=>/ {print $1, $3}')
  done
  local kib sized=$bundle
  [[ -f $bundle.tar.gz ]] && sized=$bundle.tar.gz
  kib=$(du -sk "$sized" | cut -f1)
  if ((limit > 0 && kib > limit * 1024)); then
    echo "gpu_bundle check: $sized holds $((kib / 1024)) MiB, more than $limit MiB"
    failed=1
  fi
  [[ -x $bundle/run.sh ]] || { echo "gpu_bundle check: no run.sh"; failed=1; }
  if ((failed == 0)); then
    echo "gpu_bundle check: $(ls "$bundle"/bin | wc -l) binaries, $(find "$bundle"/lib -type f | wc -l) bundled libraries, $((kib / 1024)) MiB ($(basename "$sized")): every library is bundled, CUDA's or the C/C++ runtime's"
  fi
  return $failed
}

case "${1:-}" in
  pack) pack "$2" "$3" ;;
  check) check "$2" "${3:-$max_mib}" ;;
  *) echo "usage: $0 pack BUILD_DIR BUNDLE_DIR | check BUNDLE_DIR [MAX_MIB]"; exit 2 ;;
esac
