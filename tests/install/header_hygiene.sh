#!/bin/sh
# Every installed header compiles alone, and none includes an OS, bus or third-party header
# itself (<poll.h>, <sys/...>, <linux/...>, <netinet/...>, libusb, hidapi, Eigen, spdlog,
# toml++, Cyclone DDS): a console application needs only the C++ standard library and mrskin.
# System headers that the standard library pulls in are not ours and are not counted.
# usage: header_hygiene.sh CXX SOURCE_ROOT INCLUDE_DIR...
set -eu
cxx=$1 root=$2
shift 2
dirs=""
for d in "$@"; do dirs="$dirs $(cd "$d" && pwd)"; done
includes=""
for d in $dirs; do includes="$includes -I$d"; done
forbidden='/poll\.h$|/sys/|/linux/|/netinet/|/arpa/|libusb|hidapi|/eigen3/|/spdlog/|/toml\+\+/|/dds/|/ddsc/|/fmt/'
status=0
count=0
ours=0
for d in $dirs; do
  for h in $(cd "$d" && find mrskin -name '*.hpp' | sort); do
    count=$((count + 1))
    # shellcheck disable=SC2086
    if ! out=$("$cxx" -std=c++20 -fsyntax-only -H -x c++ $includes "$d/$h" 2>&1); then
      echo "FAIL: $h does not compile alone:"
      echo "$out" | grep -v '^\.' | head -10
      status=1
      continue
    fi
    # -H prints one line per include, its depth in dots; a header's parent is the last line one
    # dot shallower. Flag a forbidden header whose parent is one of ours.
    bad=$(echo "$out" | awk -v root="$root" -v top="$d/$h" -v pat="$forbidden" '
      /^\.+ / {
        depth = index($0, " ") - 1
        path = substr($0, depth + 2)
        stack[depth] = path
        parent = depth == 1 ? top : stack[depth - 1]
        if (path ~ pat && index(parent, root) == 1) print parent " -> " path
      }')
    # A header that a standard header already pulled in is printed only there: check our own
    # direct includes too.
    direct=$(grep -E '^[[:space:]]*#[[:space:]]*include[[:space:]]*<' "$d/$h" | sed -E 's/.*<([^>]*)>.*/\1/' |
      grep -E "^(poll\.h|sys/|linux/|netinet/|arpa/|libusb|hidapi|eigen3/|Eigen/|spdlog/|toml\+\+/|dds/|fmt/)" || true)
    if [ -n "$direct" ]; then
      bad="$bad
$(echo "$direct" | sed "s|^|$h -> <|; s|$|>|")"
    fi
    bad=$(echo "$bad" | sed '/^$/d')
    if echo "$out" | awk -v root="$root" 'index($0, root) > 0 { found = 1 } END { exit !found }'; then
      ours=$((ours + 1))
    fi
    if [ -n "$bad" ]; then
      echo "FAIL: $h pulls in:"
      echo "$bad" | sort -u | sed "s|$root/||g"
      status=1
    fi
  done
done
# A path mismatch between root and the -H output would make every check above pass vacuously.
if [ "$count" -eq 0 ] || [ "$ours" -eq 0 ]; then
  echo "FAIL: $count headers found, $ours with one of ours in their -H output (is $root the source root?)"
  status=1
fi
[ "$status" -eq 0 ] && echo "header hygiene: $count installed headers compile alone and include only the standard library and mrskin"
exit "$status"
