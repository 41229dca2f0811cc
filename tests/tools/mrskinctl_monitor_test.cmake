# mrskinctl monitor on mock:// (piped: plain lines; --json: one object per line; an injected fault
# shows), and --help of the bridge commands.
# cmake -DMRSKINCTL=path/to/mrskinctl -P mrskinctl_monitor_test.cmake
include(${CMAKE_CURRENT_LIST_DIR}/cli_check.cmake)

string(ASCII 27 esc)

# Piped: plain lines, no escape sequences, the idle unit's state.
run(0 monitor --device "mock://?seed=1" --duration 0.3 --period-ms 100)
foreach(t "t=" "state DISABLED fault none" "force max" "displacement max" "current max" "coil est. max")
  expect("${t}" "${out}")
endforeach()
expect_not("${esc}" "${out}")

# --json: one object per line with the grid arrays (13 fluid cells, 12 valves on the 5 x 5).
run(0 monitor --device "mock://?seed=1" --duration 0.3 --period-ms 100 --json)
string(REGEX MATCH "^[^\n]*" first "${out}")
string(JSON state GET "${first}" state)
string(JSON cells LENGTH "${first}" force_n)
string(JSON depths LENGTH "${first}" displacement_m)
string(JSON valves LENGTH "${first}" current_a)
string(JSON temps LENGTH "${first}" temperature_c)
string(JSON rows GET "${first}" rows)
if(NOT state STREQUAL "DISABLED" OR NOT cells EQUAL 13 OR NOT depths EQUAL 13 OR NOT valves EQUAL 12 OR NOT temps EQUAL 12
   OR NOT rows EQUAL 5)
  message(FATAL_ERROR "unexpected --json line: ${first}")
endif()

# The mock's injected bus-off fault shows as the state and the cause.
run(0 monitor --device "mock://?seed=2&faults=busoff:0.05" --duration 1.0 --period-ms 100)
expect("state FAULT fault bus off" "${out}")
run(0 monitor --device "mock://?seed=2&faults=busoff:0.05" --duration 1.0 --period-ms 100 --json)
expect("\"fault\":\"bus off\"" "${out}")

# A forced colour heatmap (what a terminal gets) draws in place.
run(0 monitor --device "mock://?seed=1" --duration 0.2 --color always)
expect("${esc}[H" "${out}")
expect("${esc}[48;5;" "${out}")
run(0 monitor --device "mock://?seed=1" --duration 0.2 --color never)
expect_not("${esc}[48;5;" "${out}")

# Every command has --help; a bad URI is a usage error.
run(0 monitor --help)
foreach(t "--device" "--bridge" "--duration" "--period-ms" "Exit codes")
  expect("${t}" "${out}")
endforeach()
foreach(cmd enable disable estop fault)
  run(0 ${cmd} --help)
  expect("--bridge" "${out}")
  expect("Exit codes" "${out}")
endforeach()
run(2 monitor --device "mock://no-such-skin" --duration 0.1)
expect("no-such-skin" "${err}")
