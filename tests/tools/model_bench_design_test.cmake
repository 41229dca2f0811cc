# mrskin-model-bench --suite design --quick (docs/model.md, "The design study"): exits 0 only when
# the designed profile meets the constraints and covers the organs at least as the base does;
# here also: designed.toml loads (mrskinctl model, and as a mock:// unit), the coverage table
# says so, and a plot exists per parameter. Run with -DBENCH=... -DCTL=... -DWORK=...
include(${CMAKE_CURRENT_LIST_DIR}/cli_check.cmake)  # expect()
file(REMOVE_RECURSE ${WORK})
file(MAKE_DIRECTORY ${WORK})
execute_process(COMMAND ${BENCH} --suite design --quick --out ${WORK} RESULT_VARIABLE code
                OUTPUT_VARIABLE out ERROR_VARIABLE err TIMEOUT 400)
if(NOT code EQUAL 0)
  message(FATAL_ERROR "--suite design --quick: exit ${code}\n${out}\n${err}")
endif()
expect("designed: meets every constraint" "${out}")

foreach(key turns gap_m length_m width_m spacer_gap_m thickness_m pretension_N_per_m initial_pressure_Pa range_use)
  if(NOT EXISTS ${WORK}/design_${key}.svg)
    message(FATAL_ERROR "no plot design_${key}.svg:\n${out}")
  endif()
endforeach()

# The smallest organ coverage of the designed profile against the base's, from the CSV.
file(STRINGS ${WORK}/design_coverage.csv rows)
set(min_base 2)
set(min_designed 2)
foreach(row IN LISTS rows)
  string(REPLACE "," ";" f "${row}")
  list(GET f 0 profile)
  list(GET f 1 scene)
  list(GET f -1 coverage)
  if(scene MATCHES "^(hand|neck|abdomen|thigh|back|stomach)$")
    if(profile STREQUAL "mr-skin-5x5" AND coverage LESS min_base)
      set(min_base ${coverage})
    elseif(profile STREQUAL "designed" AND coverage LESS min_designed)
      set(min_designed ${coverage})
    endif()
  endif()
endforeach()
if(min_base EQUAL 2 OR min_designed EQUAL 2 OR min_designed LESS min_base)
  message(FATAL_ERROR "organ coverage: designed ${min_designed} against the default's ${min_base}")
endif()

execute_process(COMMAND ${CTL} model --profile ${WORK}/designed.toml profile RESULT_VARIABLE code
                OUTPUT_VARIABLE out ERROR_VARIABLE err TIMEOUT 60)
if(NOT code EQUAL 0)
  message(FATAL_ERROR "mrskinctl model --profile designed.toml: exit ${code}\n${out}\n${err}")
endif()
expect("\"name\": \"designed\"" "${out}")
execute_process(COMMAND ${CTL} selftest --device mock://${WORK}/designed.toml RESULT_VARIABLE code
                OUTPUT_VARIABLE out ERROR_VARIABLE err TIMEOUT 60)
if(NOT code EQUAL 0)
  message(FATAL_ERROR "mrskinctl selftest --device mock://designed.toml: exit ${code}\n${out}\n${err}")
endif()
message(STATUS "design suite: designed.toml loads, meets the constraints, covers the organs "
               "${min_designed} (default ${min_base}); plots written")
