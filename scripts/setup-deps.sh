#!/usr/bin/env bash
# Installs the Debian 12 packages mrskin needs, in sets, and only the missing ones. Quiet (prints
# nothing) when everything is already there. Needs root or password-less sudo to install;
# otherwise prints the exact apt-get command to run and exits with status 1.
#
#   scripts/setup-deps.sh [SET...]          install the sets (default: all of them)
#   scripts/setup-deps.sh --print [SET...]  print the sets' packages, one line, install nothing
#
# Sets (each installs everything its commands need on a bare Debian 12, debootstrap minbase):
#   run    build the demo preset and run scripts/demo.sh (the daemon on the mock device)
#   build  every preset's build: tests, benchmarks, the Python module, clang and its fuzzers
#   test   build, and what the tests run: valgrind, can-utils, the Fast DDS peer, the QEMU VM
#          (qemu, busybox, cpio, iproute2), pytest, bash-completion
#   lint   scripts/lint.sh (clang-format, clang-tidy)
#   package  scripts/package.sh and its test (debhelper, lintian, mmdebstrap)
set -euo pipefail

declare -A SET
# compilers, build tools and the libraries the libraries and tools link (Debian 12's packages);
# Cyclone DDS for the ROS 2 topics (its C API and its IDL compiler, idlc)
SET[run]="g++ cmake ninja-build pkg-config
  libhidapi-dev libusb-1.0-0-dev libeigen3-dev libspdlog-dev libcli11-dev libtomlplusplus-dev
  nlohmann-json3-dev libcap-dev libopenigtlink-dev cyclonedds-dev cyclonedds-tools"
# test frameworks and benchmarks; the Python module; clang 14 with its sanitizer and fuzzer runtime;
# the man pages (help2man, from each tool's --help)
SET[build]="${SET[run]}
  libgtest-dev libgmock-dev librapidcheck-dev libbenchmark-dev
  python3-dev pybind11-dev python3-numpy
  clang clang-14 libclang-rt-14-dev
  help2man"
# callgrind gates, the CAN peer (candump, cansend), the ROS 2 peer on Fast DDS (tests/interop),
# the kernel tests in a QEMU VM (tests/system, docs/vm-tests.md: the host's ip for the guest's
# vcan, busybox and cpio for its init), pytest
SET[test]="${SET[build]}
  valgrind can-utils libfastrtps-dev
  qemu-system-x86 busybox-static cpio iproute2
  python3-pytest bash-completion"
SET[lint]="clang-format clang-tidy"
# scripts/package.sh and ctest --preset package (docs/install.md): the Debian packages from the
# release build, lintian, the minimal Debian 12 root of the package test
SET[package]="${SET[build]}
  debhelper dh-python dpkg-dev fakeroot lintian mmdebstrap"

print=0
if [[ ${1:-} == --print ]]; then
  print=1
  shift
fi
sets=("$@")
((${#sets[@]} > 0)) || sets=(run build test lint package)
PACKAGES=()
for name in "${sets[@]}"; do
  if [[ -z ${SET[$name]+set} ]]; then
    echo "setup-deps: no set '$name': use run, build, test, lint or package" >&2
    exit 2
  fi
  read -r -a pkgs <<<"$(echo ${SET[$name]})"
  PACKAGES+=("${pkgs[@]}")
done
mapfile -t PACKAGES < <(printf '%s\n' "${PACKAGES[@]}" | awk '!seen[$0]++')
if ((print)); then
  echo "${PACKAGES[*]}"
  exit 0
fi

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
