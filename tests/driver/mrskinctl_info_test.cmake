# mrskinctl info against the mock: what it prints, and its exit codes on failure.
# cmake -DMRSKINCTL=path/to/mrskinctl -P mrskinctl_info_test.cmake
include(${CMAKE_CURRENT_LIST_DIR}/../tools/cli_check.cmake)

function(run_info expected_exit)
  run(${expected_exit} info ${ARGN})
  set(out "${out}" PARENT_SCOPE)
  set(err "${err}" PARENT_SCOPE)
endfunction()

# Identity, protocol, profile, layout, limits, calibration, state and statistics.
run_info(0 --device "mock://?seed=1" --sample 0.05)
foreach(t "protocol     v1.2 (library speaks v1.2)" "profile      mr-skin-5x5" "grid         5 x 5: 13 fluid cells, 12 valves"
          "sensors      12 displacement sensors in m" "limits       current 0..0.1000 A in steps of 25.0 uA"
          "heartbeat timeout 0.100 s" "state        DISABLED" "calibration" "version = 1" "statistics over 0.05 s"
          "round trip")
  expect("${t}" "${out}")
endforeach()

run_info(0 --device "mock://fingertip-16x16?seed=1" --sample 0.05 --json)
foreach(t "\"profile\": {\"name\": \"fingertip-16x16\"" "\"rows\": 16" "\"max_current_a\": 0.04" "\"stats\": {")
  expect("${t}" "${out}")
endforeach()

# A fault during the sample: --log prints the decoded fault report.
run_info(0 --device "mock://?seed=2&faults=busoff:0.02" --sample 0.15 --log)
foreach(t "state        FAULT (fault: bus off)" "fault: bus off at" "packets before it, oldest first" "telemetry"
          "sensors 0..11 [m]:" "status        FAULT (fault: bus off)")
  expect("${t}" "${out}")
endforeach()
run_info(0 --device "mock://?seed=2&faults=busoff:0.02" --sample 0.15 --log --json)
expect("\"log\": {\"kind\": \"fault\", \"fault\": \"bus off\", \"records\": [" "${out}")

# Failures: a clear message on stderr and a non-zero exit (tools/common/exit_codes.hpp).
run_info(2 --device "mock://no-such-skin")
expect("\"no-such-skin\" not found; searched" "${err}")
expect("available: " "${err}")
run_info(2 --device "mock://?rows=3")
expect("the grid comes from the device profile" "${err}")
run_info(3 --device "hid://0001:0002")
expect("no MR skin for hid://0001:0002" "${err}")
run_info(2 --device "hid://zz")
expect("hid://" "${err}")
