# mrskinctl set, selftest, calibrate, record and replay against mock:// (simulated clock: fixed seeds,
# deterministic, no timing asserts). Included from tests/tools/CMakeLists.txt.
foreach(part set selftest calibrate calibrate_dry calibrate_refuse calibrate_faults calibrate_zero calibrate_noisy record budget)
  add_test(NAME ToolsMrskinctlDevice_${part}
           COMMAND ${CMAKE_COMMAND} -DMRSKINCTL=$<TARGET_FILE:mrskinctl> -DPART=${part}
                   -DWORK=${CMAKE_CURRENT_BINARY_DIR}/mrskinctl_device_${part}
                   -P ${CMAKE_CURRENT_SOURCE_DIR}/mrskinctl_device_test.cmake)
  # single_thread: one process on a simulated clock, nothing for ThreadSanitizer to find (the
  # tsan preset skips them; they take minutes there).
  set_tests_properties(ToolsMrskinctlDevice_${part} PROPERTIES LABELS "tools;single_thread" TIMEOUT 300)
endforeach()
