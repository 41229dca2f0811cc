#!/bin/sh
# The libraries are built with hidden visibility: every symbol of ours that a library exports is
# named in an installed header (its function, class or variable), and no private part is exported
# (an Impl, an anonymous namespace, the stream sources' parsers, the OS seams of the transports).
# usage: exported_symbols.sh NM INCLUDE_DIRS(colon-separated) LIB...
set -eu
nm=$1 include_dirs=$2
shift 2
words=$(mktemp)
trap 'rm -f "$words"' EXIT
# Every identifier of the installed headers, one per line.
echo "$include_dirs" | tr ':' '\n' | while read -r d; do
  find "$d" -name '*.hpp' -exec cat {} +
done | tr -c 'A-Za-z0-9_' '\n' | grep -v '^$' | sort -u >"$words"
private='::Impl\b|::Impl::|\(anonymous namespace\)|mrskin::bridge::sources::|LibusbApi|CanSocketApi|::detail::'
status=0
for lib in "$@"; do
  name=$(basename "$lib")
  if ! symbols=$("$nm" -DC --defined-only "$lib" | sed 's/^[0-9a-f]* [A-Za-z] //'); then
    echo "FAIL: $nm could not read $lib"
    status=1
    continue
  fi
  ours=$(echo "$symbols" | grep 'mrskin::' || true)
  if [ -z "$ours" ]; then
    echo "FAIL: $name exports nothing of mrskin (the check would prove nothing)"
    status=1
    continue
  fi
  bad=$(echo "$ours" | grep -E "$private" || true)
  if [ -n "$bad" ]; then
    echo "FAIL: $name exports private symbols:"
    echo "$bad" | head -10
    status=1
  fi
  # The name a symbol defines: drop 'typeinfo for ' and the like, the parameter list, template
  # arguments and ABI tags, then keep the last component. Symbols of std templates over our types
  # (std::vector<mrskin::...>) are the standard library's and are skipped.
  unnamed=$(echo "$ours" | grep -v '^std::\|^void std::\|^[a-z_:<>, ]* std::' |
    sed -e 's/^\(typeinfo name for\|typeinfo for\|vtable for\|VTT for\|guard variable for\) //' \
        -e 's/\[abi:[a-z0-9]*\]//g' -e 's/(.*//' -e 's/^.* \(mrskin::\)/\1/' |
    sed -e ':a' -e 's/<[^<>]*>//g' -e 'ta' | sed 's/.*:://' | sed 's/^~//' | sort -u |
    while read -r id; do
      case "$id" in operator*) continue ;; esac
      grep -qx "$id" "$words" || echo "$id"
    done)
  if [ -n "$unnamed" ]; then
    echo "FAIL: $name exports names that no installed header declares:"
    echo "$unnamed" | head -20
    status=1
  fi
  echo "$name: $(echo "$ours" | wc -l) symbols of mrskin exported"
done
[ "$status" -eq 0 ] && echo "exported symbols: only what the installed headers name, no private part"
exit "$status"
