# Shared by the cmake -P tests of the command-line tools: run ${MRSKINCTL} and check what it
# printed. include(${CMAKE_CURRENT_LIST_DIR}/.../cli_check.cmake) from the test script.

# run(EXPECTED_EXIT ARGS...): runs mrskinctl ARGS, fails unless it exits EXPECTED_EXIT; leaves its
# stdout in `out` and stderr in `err`.
function(run expected_exit)
  execute_process(COMMAND ${MRSKINCTL} ${ARGN} RESULT_VARIABLE code OUTPUT_VARIABLE out ERROR_VARIABLE err
                  TIMEOUT 120)
  if(NOT code EQUAL expected_exit)
    message(FATAL_ERROR "mrskinctl ${ARGN}: exit ${code}, expected ${expected_exit}\n${out}\n${err}")
  endif()
  set(out "${out}" PARENT_SCOPE)
  set(err "${err}" PARENT_SCOPE)
endfunction()

function(expect text haystack)
  string(FIND "${haystack}" "${text}" at)
  if(at EQUAL -1)
    message(FATAL_ERROR "expected '${text}' in:\n${haystack}")
  endif()
endfunction()

function(expect_not text haystack)
  string(FIND "${haystack}" "${text}" at)
  if(NOT at EQUAL -1)
    message(FATAL_ERROR "did not expect '${text}' in:\n${haystack}")
  endif()
endfunction()

# --json output must parse: string(JSON) fails on malformed text.
function(expect_json_field json field expected)
  string(JSON value ERROR_VARIABLE json_error GET "${json}" ${field})
  if(json_error)
    message(FATAL_ERROR "not JSON or no '${field}': ${json_error}\n${json}")
  endif()
  if(NOT "${value}" STREQUAL "${expected}")
    message(FATAL_ERROR "${field} = '${value}', expected '${expected}'\n${json}")
  endif()
endfunction()
