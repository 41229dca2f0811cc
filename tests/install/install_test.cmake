# cmake -P script run by the install.consumer test (see CMakeLists.txt for its -D inputs):
#  1. cmake --install BUILD_DIR into a fresh prefix under WORK_DIR;
#  2. checks the installed tree: versioned shared libraries with their soname, headers, tools,
#     the udev rule and the CMake package files;
#  3. configures, builds and runs consumer/ against the prefix; its output must name VERSION.
cmake_minimum_required(VERSION 3.25)

foreach(_var BUILD_DIR WORK_DIR CONSUMER_SOURCE_DIR GENERATOR CXX_COMPILER LIBDIR INCLUDEDIR BINDIR
             VERSION)
  if(NOT DEFINED ${_var} OR "${${_var}}" STREQUAL "")
    message(FATAL_ERROR "install_test.cmake: -D${_var}=... is required")
  endif()
endforeach()
string(REPLACE "|" ";" LIB_FILES "${LIB_FILES}")
string(REPLACE "|" ";" TOOLS "${TOOLS}")

set(_prefix ${WORK_DIR}/prefix)
set(_consumer_build ${WORK_DIR}/consumer-build)
file(REMOVE_RECURSE ${WORK_DIR})
file(MAKE_DIRECTORY ${WORK_DIR})

function(run_step what)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE _rc OUTPUT_VARIABLE _out ERROR_VARIABLE _out)
  if(NOT _rc EQUAL 0)
    message(FATAL_ERROR "${what} failed (${_rc}):\n  ${ARGN}\n${_out}")
  endif()
  message(STATUS "${what}: ok")
  set(step_output "${_out}" PARENT_SCOPE)
endfunction()

set(_errors "")
macro(expect_file path)
  if(NOT EXISTS "${_prefix}/${path}")
    string(APPEND _errors "  missing: ${path}\n")
  endif()
endmacro()

# --- 1. install -----------------------------------------------------------------------
run_step("cmake --install" ${CMAKE_COMMAND} --install ${BUILD_DIR} --prefix ${_prefix})

# --- 2. installed tree ------------------------------------------------------------------
if(NOT LIB_FILES)
  string(APPEND _errors "  no shared library target was given to check\n")
endif()
foreach(_entry IN LISTS LIB_FILES)
  # <real file name>:<soname>, e.g. libmrskin_driver.so.0.1.0:libmrskin_driver.so.0.1
  string(REPLACE ":" ";" _entry "${_entry}")
  list(GET _entry 0 _file)
  list(GET _entry 1 _soname)
  string(REGEX REPLACE "\\.so\\..*$" ".so" _link "${_file}")
  if(_file STREQUAL _link OR _soname STREQUAL _link)
    string(APPEND _errors "  ${_file}: not versioned (soname ${_soname})\n")
  endif()
  expect_file(${LIBDIR}/${_file})
  expect_file(${LIBDIR}/${_soname})
  expect_file(${LIBDIR}/${_link})
  if(EXISTS "${_prefix}/${LIBDIR}/${_file}" AND READELF)
    execute_process(COMMAND ${READELF} -d ${_prefix}/${LIBDIR}/${_file}
                    OUTPUT_VARIABLE _dyn RESULT_VARIABLE _rc)
    if(NOT _rc EQUAL 0 OR NOT _dyn MATCHES "\\(SONAME\\)[^\n]*\\[${_soname}\\]")
      string(APPEND _errors "  ${LIBDIR}/${_file}: DT_SONAME is not ${_soname}\n")
    endif()
  endif()
endforeach()
expect_file(${INCLUDEDIR}/mrskin/driver/version.hpp)
expect_file(${INCLUDEDIR}/mrskin/protocol/messages.hpp)
foreach(_tool IN LISTS TOOLS)
  expect_file(${BINDIR}/${_tool})
endforeach()
if(NOT UDEVRULESDIR)
  set(UDEVRULESDIR lib/udev/rules.d)
endif()
expect_file(${UDEVRULESDIR}/70-mrskin.rules)
foreach(_f mrskinConfig.cmake mrskinConfigVersion.cmake mrskinTargets.cmake)
  expect_file(${LIBDIR}/cmake/mrskin/${_f})
endforeach()
if(_errors)
  message(FATAL_ERROR "installed tree ${_prefix} is incomplete:\n${_errors}")
endif()
message(STATUS "installed tree: ok")

# --- 3. consumer project ----------------------------------------------------------------
set(_configure ${CMAKE_COMMAND} -S ${CONSUMER_SOURCE_DIR} -B ${_consumer_build} -G ${GENERATOR}
    -DCMAKE_CXX_COMPILER=${CXX_COMPILER} -DCMAKE_PREFIX_PATH=${_prefix} -DCMAKE_FIND_USE_PACKAGE_REGISTRY=OFF)
if(MAKE_PROGRAM)
  list(APPEND _configure -DCMAKE_MAKE_PROGRAM=${MAKE_PROGRAM})
endif()
if(BUILD_TYPE)
  list(APPEND _configure -DCMAKE_BUILD_TYPE=${BUILD_TYPE})
endif()
if(CXX_FLAGS)
  list(APPEND _configure -DCMAKE_CXX_FLAGS=${CXX_FLAGS} -DCMAKE_EXE_LINKER_FLAGS=${CXX_FLAGS})
endif()
run_step("configure consumer" ${_configure})
run_step("build consumer" ${CMAKE_COMMAND} --build ${_consumer_build})

# The consumer must use the installed copy, not the build tree's.
file(STRINGS ${_consumer_build}/CMakeCache.txt _dir_line REGEX "^mrskin_DIR:")
string(REGEX REPLACE "^[^=]*=" "" _mrskin_dir "${_dir_line}")
file(REAL_PATH "${_mrskin_dir}" _mrskin_dir)
file(REAL_PATH "${_prefix}" _real_prefix)
string(FIND "${_mrskin_dir}/" "${_real_prefix}/" _pos)
if(NOT _pos EQUAL 0)
  message(FATAL_ERROR "consumer found mrskin in ${_mrskin_dir}, not under ${_real_prefix}")
endif()

run_step("run consumer" ${_consumer_build}/mrskin_consumer)
string(STRIP "${step_output}" step_output)
message(STATUS "consumer says: ${step_output}")
string(REPLACE "." "\\." _version_re "${VERSION}")
if(NOT step_output MATCHES "mrskin library ${_version_re}([^0-9.]|$)")
  message(FATAL_ERROR "consumer output does not name version ${VERSION}:\n${step_output}")
endif()
