# cmake -DDIR=<dir of generated magvec_lcm/*.hpp> -P harden_generated.cmake
# lcm-gen's C++ string decoder (LCM 1.4/1.5) checks only `len > maxlen - pos` and then copies
# `len - 1` bytes: a length of 0 or below makes std::string::assign throw std::length_error (out of
# decode(), through LCM's C dispatcher: magvecd would terminate on one malformed command packet),
# and INT32_MIN overflows `len - 1` (undefined behaviour, in practice a 2 GiB read). Every string
# length must count at least its terminating NUL; the check is added to each generated decoder.
# The string must also be one C string: its last byte the NUL and no NUL before it (the encoder
# writes strlen() bytes, so a decoded string with an embedded NUL would re-encode to fewer bytes than
# getEncodedSize() announces). A generator whose output no longer has the expected pattern fails
# the build here.
cmake_minimum_required(VERSION 3.22)
file(GLOB headers ${DIR}/*.hpp)
if(NOT headers)
  message(FATAL_ERROR "harden_generated.cmake: no headers in '${DIR}'")
endif()
foreach(h ${headers})
  file(READ ${h} text)
  string(REGEX MATCHALL "\\.assign\\([^;]*_len__ - 1\\);" assigns "${text}")
  string(REGEX MATCHALL "if\\(__[A-Za-z0-9_]+_len__ > maxlen - pos\\) return -1;" checks "${text}")
  list(LENGTH assigns n_assign)
  list(LENGTH checks n_check)
  if(NOT n_assign EQUAL n_check)
    if(text MATCHES "_len__ < 1 \\|\\|")
      continue()  # already hardened
    endif()
    message(FATAL_ERROR "harden_generated.cmake: ${h}: ${n_assign} string decodes but ${n_check} "
                        "length checks of the known form (lcm-gen changed?)")
  endif()
  string(REGEX REPLACE "if\\(__([A-Za-z0-9_]+)_len__ > maxlen - pos\\) return -1;"
                       "if(__\\1_len__ < 1 || __\\1_len__ > maxlen - pos || memchr(((const char*)buf) + offset + pos, 0, __\\1_len__) != ((const char*)buf) + offset + pos + __\\1_len__ - 1) return -1;"
                       text "${text}")
  file(WRITE ${h} "${text}")
endforeach()
