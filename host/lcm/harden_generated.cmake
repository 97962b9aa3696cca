# cmake -DDIR=<dir of generated magvec_lcm/*.hpp> -P harden_generated.cmake
# lcm-gen's C++ string decoder (LCM 1.3-1.5) checks only `len > maxlen - pos` and then copies
# `len - 1` bytes: a length of 0 or below makes std::string::assign throw std::length_error (out of
# decode(), through LCM's C dispatcher: magvecd would terminate on one malformed command packet),
# and INT32_MIN overflows `len - 1` (undefined behaviour, in practice a 2 GiB read). Every string
# length must count at least its terminating NUL; the check is added to each generated decoder.
# The string must also be one C string: its last byte the NUL and no NUL before it (the encoder
# writes strlen() bytes, so a decoded string with an embedded NUL would re-encode to fewer bytes than
# getEncodedSize() announces).
# A variable-length array (`T items[count]`) is decoded as `items.resize(count)` before any element
# is read: a negative count throws std::length_error, and INT32_MAX allocates (and value-initialises)
# 2^31 elements before the buffer runs out. Every element takes at least one byte, so a count below
# 0 or beyond the bytes left is rejected before the resize.
# A generator whose output no longer has the expected patterns fails the build here.
cmake_minimum_required(VERSION 3.22)
file(GLOB headers ${DIR}/*.hpp)
if(NOT headers)
  message(FATAL_ERROR "harden_generated.cmake: no headers in '${DIR}'")
endif()
foreach(h ${headers})
  file(READ ${h} text)
  # Strings.
  string(REGEX MATCHALL "\\.assign\\([^;]*_len__ - 1\\);" assigns "${text}")
  string(REGEX MATCHALL "if\\(__[A-Za-z0-9_]+_len__ > maxlen - pos\\) return -1;" checks "${text}")
  list(LENGTH assigns n_assign)
  list(LENGTH checks n_check)
  if(NOT n_assign EQUAL n_check)
    if(NOT text MATCHES "_len__ < 1 \\|\\|")
      message(FATAL_ERROR "harden_generated.cmake: ${h}: ${n_assign} string decodes but ${n_check} "
                          "length checks of the known form (lcm-gen changed?)")
    endif()
  else()
    string(REGEX REPLACE "if\\(__([A-Za-z0-9_]+)_len__ > maxlen - pos\\) return -1;"
                         "if(__\\1_len__ < 1 || __\\1_len__ > maxlen - pos || memchr(((const char*)buf) + offset + pos, 0, __\\1_len__) != ((const char*)buf) + offset + pos + __\\1_len__ - 1) return -1;"
                         text "${text}")
  endif()
  # Variable-length arrays: every resize in a decoder is `this->items.resize(this->count);` (the
  # encoders never resize).
  string(REGEX MATCHALL "\\.resize\\(" resizes "${text}")
  # (No ';' in MATCHALL patterns: a match holding one would count as two list elements.)
  string(REGEX MATCHALL "this->[A-Za-z0-9_]+\\.resize\\(this->[A-Za-z0-9_]+\\)" known "${text}")
  string(REGEX MATCHALL "< 0 \\|\\| this->[A-Za-z0-9_]+ > maxlen - pos\\) return -1" guarded
         "${text}")
  list(LENGTH resizes n_resize)
  list(LENGTH known n_known)
  list(LENGTH guarded n_guarded)
  if(NOT n_resize EQUAL n_known)
    message(FATAL_ERROR "harden_generated.cmake: ${h}: ${n_resize} resizes but ${n_known} of the "
                        "known form (lcm-gen changed?)")
  endif()
  if(n_guarded EQUAL 0)
    string(REGEX REPLACE "(this->[A-Za-z0-9_]+\\.resize\\(this->([A-Za-z0-9_]+)\\);)"
                         "if(this->\\2 < 0 || this->\\2 > maxlen - pos) return -1;\n    \\1"
                         text "${text}")
  elseif(NOT n_guarded EQUAL n_known)
    message(FATAL_ERROR "harden_generated.cmake: ${h}: partly hardened (${n_guarded} of ${n_known})")
  endif()
  file(WRITE ${h} "${text}")
endforeach()
