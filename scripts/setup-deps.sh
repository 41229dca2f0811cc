#!/usr/bin/env bash
# Installs the Debian 12 packages mrskin needs to build, test and lint, and only the missing ones.
# Quiet (prints nothing) when everything is already there. Needs root or password-less sudo to
# install; otherwise prints the exact apt-get command to run and exits with status 1.
set -euo pipefail

PACKAGES=(
  # compilers and build tools
  g++ clang clang-14 libclang-rt-14-dev cmake ninja-build pkg-config
  # libraries (Debian 12's packages)
  libhidapi-dev libusb-1.0-0-dev libeigen3-dev libspdlog-dev libcli11-dev
  libtomlplusplus-dev nlohmann-json3-dev libcap-dev libopenigtlink-dev
  # ROS 2 topics over DDS: Cyclone's C API and its IDL compiler (idlc)
  cyclonedds-dev cyclonedds-tools
  # tests, benchmarks and test peers
  libgtest-dev libgmock-dev librapidcheck-dev libbenchmark-dev valgrind can-utils
  # the ROS 2 interop peer on Fast DDS (tests/interop)
  libfastrtps-dev
  # kernel integration tests in a QEMU VM (tests/system, docs/vm-tests.md)
  qemu-system-x86 busybox-static cpio
  # lint
  clang-format clang-tidy
  # Python bindings (python/, docs/python.md) and their tests
  python3-dev pybind11-dev python3-numpy python3-pytest
)

missing=()
for pkg in "${PACKAGES[@]}"; do
  status=$(dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null || true)
  [[ $status == installed ]] || missing+=("$pkg")
done
((${#missing[@]} == 0)) && exit 0

if [[ $(id -u) -eq 0 ]]; then
  sudo=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  sudo=(sudo -n)
else
  echo "setup-deps: missing Debian packages: ${missing[*]}" >&2
  if command -v sudo >/dev/null 2>&1; then
    echo "setup-deps: sudo needs a password; run this, then try again:" >&2
    echo "sudo apt-get update && sudo apt-get install -y --no-install-recommends ${missing[*]}" >&2
  else
    echo "setup-deps: not root and no sudo; run this as root, then try again:" >&2
    echo "apt-get update && apt-get install -y --no-install-recommends ${missing[*]}" >&2
  fi
  exit 1
fi

echo "setup-deps: installing ${missing[*]}"
"${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -qq
"${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
  -o Dpkg::Use-Pty=0 "${missing[@]}"
