# mrskinctl monitor, enable, disable, estop and fault: on mock:// (a cmake -P script), and against a
# mrskin-bridged on mock:// and fake daemons (gtest). Included from tests/tools/CMakeLists.txt
# inside if(TARGET mrskinctl).
add_test(NAME ToolsMrskinctlMonitor
         COMMAND ${CMAKE_COMMAND} -DMRSKINCTL=$<TARGET_FILE:mrskinctl> -P
                 ${CMAKE_CURRENT_SOURCE_DIR}/mrskinctl_monitor_test.cmake)
set_tests_properties(ToolsMrskinctlMonitor PROPERTIES LABELS tools TIMEOUT 300 ENVIRONMENT MRSKIN_TIME_SCALE=10)

if(TARGET mrskin_bridged_core AND TARGET mrskin-bridged)
  mrskin_add_test(NAME mrskinctl_bridge_test SOURCES mrskinctl_bridge_test.cpp LIBS mrskin_bridged_core mrskin_tools_json
                  LABELS tools)
  target_compile_definitions(mrskinctl_bridge_test PRIVATE MRSKIN_BRIDGED_EXE="$<TARGET_FILE:mrskin-bridged>"
                                                           MRSKINCTL_EXE="$<TARGET_FILE:mrskinctl>")
  add_dependencies(mrskinctl_bridge_test mrskin-bridged mrskinctl)
endif()
