#!/usr/bin/env bash
# ctest package.build_paths: no file the packages install names the checkout or the build tree
# (the install must be relocatable: tools and libraries find their data relative to themselves).
# Unpacks every .deb into one tree, as apt would install them, and searches every file's bytes
# (binaries included) for the source and build directories' absolute paths. With CONFIGURED_PREFIX
# (the build's CMAKE_INSTALL_PREFIX, /usr/local for the presets) other than /usr, no file outside
# share/doc may name it either: the packages install under /usr, and a path fixed at configure
# time (a unit's ExecStart, a library's data directory) would point at the wrong place. The docs
# may: they describe installing to /usr/local.
#
#   build_paths.sh DEB_DIR SOURCE_DIR BUILD_DIR WORK_DIR [CONFIGURED_PREFIX]
set -euo pipefail

if (($# != 4 && $# != 5)); then
  echo "usage: build_paths.sh DEB_DIR SOURCE_DIR BUILD_DIR WORK_DIR [CONFIGURED_PREFIX]" >&2
  exit 2
fi
debs=$(realpath "$1")
src=$(realpath "$2")
build=$(realpath "$3")
tree=$(realpath -m "$4")/tree
prefix=${5:-/usr}

shopt -s nullglob
deb_files=("$debs"/*.deb)
if ((${#deb_files[@]} == 0)); then
  echo "build_paths: no .deb in $debs: run scripts/package.sh first" >&2
  exit 1
fi
rm -rf "$tree"
mkdir -p "$tree"
for deb in "${deb_files[@]}"; do
  dpkg-deb -x "$deb" "$tree"
done
# Man pages are gzipped: search their text.
find "$tree" -name '*.gz' -type f -exec gunzip -f {} +
echo "build_paths: $(find "$tree" -type f | wc -l) files from ${#deb_files[@]} packages; searching for $src and $build"

found=0
# The build directory lies under the checkout here, so the checkout's path finds both; the build
# directory is searched on its own for out-of-tree builds.
for path in "$src" "$build"; do
  while IFS= read -r file; do
    found=1
    echo "build_paths: ${file#"$tree"} holds $path:" >&2
    strings -a "$file" | grep -F "$path" | sort -u | sed 's/^/    /' >&2
  done < <(grep -rlaF "$path" "$tree" || true)
done
if [[ $prefix != /usr ]]; then
  while IFS= read -r file; do
    found=1
    echo "build_paths: ${file#"$tree"} holds the configured prefix $prefix/:" >&2
    strings -a "$file" | grep -F "$prefix/" | sort -u | sed 's/^/    /' >&2
  done < <(grep -rlaF "$prefix/" "$tree" --exclude-dir=doc || true)
fi
if ((found)); then
  echo "build_paths: FAILED: installed files name the checkout, the build tree or the configured prefix (above)" >&2
  exit 1
fi
echo "build_paths: no installed file names $src or $build, nothing outside share/doc names $prefix/"
rm -rf "$tree"
