#!/bin/sh
# The simulation is a library of its own: the driver and bridge libraries define none of its
# classes (the mock, its plant, its truth, the fingertip), nor the scorer and the scenes' finger
# (libmrskin_eval), nor the inverse's offline reference (libmrskin_model_reference, tests and
# bench only); a console linked against mrskin::bridge alone needs no libmrskin_sim.
# usage: library_split.sh NM READELF LIBDRIVER LIBBRIDGE LIBSIM CONSOLE SIM_CONSOLE
set -eu
nm=$1 readelf=$2 driver=$3 bridge=$4 sim=$5 console=$6 sim_console=$7
# Classes of the simulation and the offline reference (defined symbols only: T, W, V, D, B, R in
# nm's listing).
forbidden='mrskin::sim::|mrskin::eval::|MockDevice|NetworkPlant|MockDeviceTruth|parse_mock_uri|TruthScorer|fingertip|finger\(|solve_inverse_exact|exact_rendered_forces_N'
status=0
for lib in "$driver" "$bridge"; do
  if ! symbols=$("$nm" -DC --defined-only "$lib"); then
    echo "FAIL: $nm could not read $lib"
    status=1
    continue
  fi
  found=$(echo "$symbols" | grep -E "$forbidden" || true)
  if [ -n "$found" ]; then
    echo "FAIL: $(basename "$lib") defines simulation symbols:"
    echo "$found" | head -20
    status=1
  fi
done
if ! "$nm" -DC --defined-only "$sim" | grep -q 'mrskin::sim::MockDevice::'; then
  echo "FAIL: $(basename "$sim") does not define mrskin::sim::MockDevice"
  status=1
fi
needed=$("$readelf" -d "$console" | grep NEEDED)
if echo "$needed" | grep -qE 'libmrskin_(sim|eval)'; then
  echo "FAIL: $(basename "$console") (linked against mrskin::bridge only) needs libmrskin_sim or libmrskin_eval:"
  echo "$needed"
  status=1
fi
if ! echo "$needed" | grep -q 'libmrskin_bridge'; then
  echo "FAIL: $(basename "$console") does not need libmrskin_bridge (the check would prove nothing)"
  status=1
fi
"$console" || status=1
# A console linked with mrskin::sim that registers the scheme opens mock://.
"$sim_console" || status=1
[ "$status" -eq 0 ] && echo "library split: driver and bridge carry no simulation, scorer or reference; a bridge-only console needs no libmrskin_sim or libmrskin_eval; a sim console opens mock://"
exit "$status"
