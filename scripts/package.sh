#!/usr/bin/env bash
# Builds the Debian packages from the release build (build/release, or --build-dir DIR), without
# compiling anything again: the tree is brought up to date (a no-op after scripts/test.sh), then
# dpkg-buildpackage runs debian/rules in a copy of debian/ under OUT, which installs the tree with
# cmake --install and packages it. The .deb files land in OUT (default build/package), with
# lintian's report in OUT/lintian.txt. docs/install.md, "The Debian packages".
#
#   scripts/package.sh [--build-dir DIR] [--out DIR] [--no-lintian]
set -euo pipefail
src=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)

build=$src/build/release
out=
lintian=1
while (($#)); do
  case $1 in
    --build-dir) build=$(realpath -m "$2"); shift 2 ;;
    --out) out=$(realpath -m "$2"); shift 2 ;;
    --no-lintian) lintian=0; shift ;;
    -h | --help) sed -n '2,8s/^# \{0,1\}//p' "${BASH_SOURCE[0]}"; exit 0 ;;
    *) echo "package: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
out=${out:-$build/../package}
out=$(realpath -m "$out")

die() { echo "package: $*" >&2; exit 1; }

for tool in dpkg-buildpackage dh fakeroot cmake help2man; do
  command -v "$tool" >/dev/null 2>&1 ||
    die "$tool is missing: run ./scripts/setup-deps.sh (group 'packaging')"
done
((lintian == 0)) || command -v lintian >/dev/null 2>&1 ||
  die "lintian is missing: run ./scripts/setup-deps.sh (group 'packaging'), or pass --no-lintian"

cache=$build/CMakeCache.txt
[[ -f $cache ]] || die "no build in $build: run 'cmake --preset release && cmake --build --preset release' first"
cached() { sed -n "s/^$1:[A-Z]*=//p" "$cache"; }

# What the packages need of the build: a release build without sanitizers, with the Debian
# multiarch libdir (the packages put the libraries in /usr/lib/<multiarch>), the tools and man pages.
multiarch=$(dpkg-architecture -qDEB_HOST_MULTIARCH)
[[ $(cached CMAKE_BUILD_TYPE) == Release ]] ||
  die "$build is a $(cached CMAKE_BUILD_TYPE) build; package the release preset (build/release)"
[[ -z $(cached MRSKIN_SANITIZE) ]] || die "$build is built with sanitizers; package the release preset"
[[ $(cached CMAKE_INSTALL_LIBDIR) == "lib/$multiarch" ]] ||
  die "$build installs libraries to '$(cached CMAKE_INSTALL_LIBDIR)', not lib/$multiarch (configured before" \
    "the multiarch default): run 'cmake $build -UCMAKE_INSTALL_LIBDIR' (a reconfigure; nothing recompiles)"
[[ $(cached MRSKIN_BUILD_TOOLS) != OFF ]] || die "$build has MRSKIN_BUILD_TOOLS=OFF; the packages need the tools"

version=$(sed -n 's/^CMAKE_PROJECT_VERSION:[A-Z]*=//p' "$cache")
deb_version=$(dpkg-parsechangelog -l "$src/debian/changelog" -S Version)
[[ $deb_version == "$version" ]] ||
  die "debian/changelog is at $deb_version but the project is $version: add an entry (dch -v $version)"

echo "== package: bringing $build up to date"
cmake --build "$build" -j "$(nproc 2>/dev/null || echo 2)"
for page in mrskinctl.1 mrskin-bridged.8 mrskin-model-bench.1 mrskin-follower.1; do
  [[ -f $build/docs/man/$page ]] || die "$build/docs/man/$page was not generated (help2man missing at configure time?): reconfigure"
done

echo "== package: dpkg-buildpackage in $out"
work=$out/mrskin-$version
rm -rf "$out"
mkdir -p "$work"
cp -a "$src/debian" "$work/"
(
  cd "$work"
  # nocheck: the tests ran on the build already; -b: binary packages only; -uc -us: unsigned.
  MRSKIN_BUILD_DIR=$build DEB_BUILD_OPTIONS="nocheck ${DEB_BUILD_OPTIONS:-}" \
    dpkg-buildpackage -b -uc -us --no-pre-clean
) >"$out/dpkg-buildpackage.log" 2>&1 || {
  tail -n 40 "$out/dpkg-buildpackage.log" >&2
  die "dpkg-buildpackage failed: its log is $out/dpkg-buildpackage.log"
}
rm -rf "$work"
ls -1 "$out"/*.deb

if ((lintian)); then
  echo "== package: lintian"
  # Fails on errors and on warnings that have no override (debian/*.lintian-overrides, with reasons).
  if ! lintian --fail-on error,warning --display-info --show-overrides \
    "$out"/*.changes >"$out/lintian.txt" 2>&1; then
    cat "$out/lintian.txt" >&2
    die "lintian found errors or warnings without an override: $out/lintian.txt"
  fi
  echo "package: lintian: no error, no warning without an override ($(grep -c "^I:" "$out/lintian.txt") informational tags; report in $out/lintian.txt)"
fi
