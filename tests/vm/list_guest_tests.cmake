# Build step of tests/vm: lists a guest gtest binary's cases (it is static, so it runs on the
# host) and writes the ctest include file with one test per case plus one for the binary.
# -DBIN -DNAME -DOUT -DCHECK -DLOG
execute_process(COMMAND ${BIN} --gtest_list_tests OUTPUT_VARIABLE listing RESULT_VARIABLE rc)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "${BIN} --gtest_list_tests failed (${rc})")
endif()
string(REPLACE "\n" ";" lines "${listing}")
set(suite "")
set(text "")
foreach(line IN LISTS lines)
  if(line MATCHES "^([^ #]+)\\.")
    set(suite ${CMAKE_MATCH_1})
  elseif(line MATCHES "^  ([^ #]+)")
    set(test "${NAME}.${suite}.${CMAKE_MATCH_1}")
    string(APPEND text "add_test(vm.${test} \"${CHECK}\" \"${LOG}\" test ${test})\n"
                       "set_tests_properties(vm.${test} PROPERTIES LABELS vm FIXTURES_REQUIRED magvec_vm "
                       "SKIP_RETURN_CODE 77)\n")
  endif()
endforeach()
string(APPEND text "add_test(vm.${NAME} \"${CHECK}\" \"${LOG}\" binary ${NAME})\n"
                   "set_tests_properties(vm.${NAME} PROPERTIES LABELS vm FIXTURES_REQUIRED magvec_vm)\n")
file(WRITE ${OUT} "${text}")
