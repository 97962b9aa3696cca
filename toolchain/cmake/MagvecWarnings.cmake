# Project-wide warning set; applied per target with magvec_warnings(<target>).
function(magvec_warnings target)
  target_compile_options(${target} PRIVATE
    -Wall -Wextra -Wpedantic -Wshadow -Wconversion -Wsign-conversion -Wdouble-promotion
    -Wnon-virtual-dtor -Wold-style-cast -Wcast-align -Wformat=2
    -Wimplicit-fallthrough)
  if(MAGVEC_WERROR)
    target_compile_options(${target} PRIVATE -Werror)
  endif()
endfunction()
