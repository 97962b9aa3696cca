# Project-wide warning set; applied per target with magvec_warnings(<target>).
function(magvec_warnings target)
  target_compile_options(${target} PRIVATE
    -Wall -Wextra -Wpedantic -Wshadow -Wconversion -Wsign-conversion -Wdouble-promotion
    -Wnon-virtual-dtor -Wold-style-cast -Wcast-align -Wformat=2
    -Wimplicit-fallthrough)
  if(MAGVEC_WERROR)
    target_compile_options(${target} PRIVATE -Werror)
    # Sanitizer builds (host-asan) keep -Wmaybe-uninitialized a warning, not an error: GCC's
    # manual (-fsanitize) notes that sanitizers raise its false-positive rate and recommends
    # against -Werror with sanitizers. Seen: Eigen's debug-mode check_for_aliasing on a member
    # initialised with Mat3::Identity() (GeParams in host/calibration/ekf_runner.cpp) at -O1. The
    # same code stays under -Werror=maybe-uninitialized in the host preset, where it means
    # something.
    if(MAGVEC_SANITIZE AND CMAKE_CXX_COMPILER_ID STREQUAL "GNU")
      target_compile_options(${target} PRIVATE -Wno-error=maybe-uninitialized)
    endif()
  endif()
endfunction()
