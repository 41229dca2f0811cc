#!/usr/bin/env bash
# ctest install.bash_completion: the completion scripts (tools/bash-completion) complete the
# built tools' subcommands and options, as bash-completion runs them on TAB.
#   bash_completion.sh COMPLETION_DIR TOOL_DIR...
# Exit 77 (skipped) when bash-completion is not installed.
set -euo pipefail
completions=$1
shift
for dir in "$@"; do PATH=$dir:$PATH; done
framework=/usr/share/bash-completion/bash_completion
if [[ ! -f $framework ]]; then
  echo "bash_completion: SKIPPED: $framework missing (Debian package bash-completion: run ./scripts/setup-deps.sh)"
  exit 77
fi
set +euo pipefail # bash-completion's own functions are not written for set -eu
# shellcheck source=/dev/null
source "$framework"
compopt() { :; } # the real one works only while bash runs a completion for a TAB

failures=0
# expect FUNCTION WORD... '=>' EXPECTED...: completing the last WORD offers every EXPECTED.
expect() {
  local fn=$1 words=() want=() seen=0 w
  shift
  for w in "$@"; do
    if [[ $w == "=>" ]]; then seen=1; elif ((seen)); then want+=("$w"); else words+=("$w"); fi
  done
  COMP_WORDS=("${words[@]}")
  COMP_CWORD=$((${#words[@]} - 1))
  COMP_LINE="${words[*]}"
  COMP_POINT=${#COMP_LINE}
  COMPREPLY=()
  "$fn" "${words[0]}" "${words[-1]}" "${words[-2]}"
  for w in "${want[@]}"; do
    if ! printf '%s\n' "${COMPREPLY[@]}" | grep -qxF -- "$w"; then
      echo "bash_completion: '${words[*]}<TAB>' does not offer '$w' (offers: ${COMPREPLY[*]})" >&2
      failures=$((failures + 1))
    fi
  done
}

for tool in mrskinctl mrskin-bridged mrskin-follower mrskin-model-bench; do
  # shellcheck source=/dev/null
  source "$completions/$tool"
done
expect _mrskinctl mrskinctl '' '=>' info list monitor set selftest calibrate record replay model
expect _mrskinctl mrskinctl --j '=>' --json
expect _mrskinctl mrskinctl info -- '=>' --device --sample --log
expect _mrskinctl mrskinctl set --c '=>' --currents --cell --ceiling-n
expect _mrskinctl mrskinctl info --device mo '=>' mock://
expect _mrskinctl mrskinctl monitor --color '' '=>' auto always never
expect _mrskin_bridged mrskin-bridged -- '=>' --device --scene --duration --config --stats-json
expect _mrskin_bridged mrskin-bridged --scene '' '=>' demo hand tumour
expect _mrskin_follower mrskin-follower --sc '=>' --scene
expect _mrskin_model_bench mrskin-model-bench --suite '' '=>' valve network inverse design all
expect _mrskin_model_bench mrskin-model-bench --r '=>' --reps
expect _mrskin_model_bench mrskin-model-bench --q '=>' --quick

if ((failures)); then
  echo "bash_completion: FAILED: $failures expectations not met" >&2
  exit 1
fi
echo "bash_completion: all completions offered"
