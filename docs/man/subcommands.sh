#!/usr/bin/env bash
# Writes a help2man include file (--include) holding, for each subcommand that TOOL's --help lists,
# that subcommand's own --help, so that the man page documents every subcommand's options.
# TOOL runs by name from TOOL_DIR (through PATH), so no build path appears in its usage lines.
#   subcommands.sh TOOL_DIR TOOL OUT
set -euo pipefail
if (($# != 3)); then
  echo "usage: subcommands.sh TOOL_DIR TOOL OUT" >&2
  exit 2
fi
PATH=$1:$PATH
tool=$2
out=$3

subs=$("$tool" --help | sed -n '/^Subcommands:/,/^$/s/^  \([a-z][a-z-]*\) .*/\1/p')
if [[ -z $subs ]]; then
  echo "subcommands.sh: '$tool --help' lists no subcommands" >&2
  exit 1
fi
{
  echo '[SUBCOMMAND OPTIONS]'
  echo "Each subcommand's own help, as printed by"
  echo ".BI \"$tool \" SUBCOMMAND \" --help\"."
  for sub in $subs; do
    echo ".SS \"$tool $sub\""
    echo '.nf'
    # roff: a backslash is written \e, and a line may not start with a control character.
    "$tool" "$sub" --help | sed -e 's/\\/\\e/g' -e "s/^\([.']\)/\\\\\&\1/"
    echo '.fi'
  done
} >"$out.tmp"
mv "$out.tmp" "$out"
