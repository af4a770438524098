#!/usr/bin/env bash
# Installs the Debian packages pillarseg builds with, when any is missing. FreeType, the DejaVu
# font and nlohmann-json draw `pillarseg plot`; OpenMPI runs data-parallel training (a build
# without it still works and says so when started by mpirun); python3 runs a few test scripts, and
# with numpy the Python module's tests (python/pillarseg).
# Usage: scripts/install-deps.sh [--with-torch]   (python3-torch: only for golden files and the peer benchmark)
set -euo pipefail
packages=(cmake make g++ pkg-config libeigen3-dev libyaml-cpp-dev libcli11-dev libspdlog-dev
          libfmt-dev libpng-dev libgtest-dev libgmock-dev libbenchmark-dev
          libfreetype-dev fonts-dejavu-core nlohmann-json3-dev
          libopenmpi-dev openmpi-bin python3 python3-numpy clang-14 libclang-rt-14-dev)
if [[ "${1:-}" == "--with-torch" ]]; then packages+=(python3-torch); fi
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]} == 0)); then exit 0; fi
echo "install-deps: installing ${missing[*]}"
sudo_cmd=()
if [[ $(id -u) -ne 0 ]]; then sudo_cmd=(sudo); fi
"${sudo_cmd[@]}" apt-get update -qq
DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq "${missing[@]}"
