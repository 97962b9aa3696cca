# Debian package of the host programs (CPack DEB): magvecd with its systemd unit and example
# configuration (a conffile in /etc/magvec), the magvec CLI and its report script, the LCM types
# for lcm-spy, the geomagnetic model data. Built from a host build tree by `toolchain/package`
# (cpack -G DEB; lintian; an install test in a fresh Debian root). Every install rule of the project
# takes its prefix at install time, so the same tree installs under /usr/local (`cmake --install`)
# and packages under /usr.
set(CPACK_GENERATOR DEB)
set(CPACK_PACKAGE_NAME magvec)
set(CPACK_PACKAGE_VENDOR "magvec")
set(CPACK_PACKAGE_CONTACT "magvec maintainers <maintainers@magvec.invalid>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY "strapdown magnetic vector calibration and compensation")
set(CPACK_PACKAGE_DESCRIPTION
    "magvec reads a triaxial fluxgate magnetometer (SPI ADC or serial) and an
INS (CAN), estimates and removes the magnetometer's scale, non-orthogonality,
offset and misalignment to the INS, and outputs the calibrated field in
East/North/Up with the total field. This package holds the daemon magvecd
(systemd service, LCM output), the magvec command-line tool for batch
calibration, replay and reports, and the LCM message types for lcm-spy.")
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_STRIP_FILES ON)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)
set(CPACK_DEBIAN_PACKAGE_SECTION science)
set(CPACK_DEBIAN_PACKAGE_PRIORITY optional)
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)
# The report script and the command-line plotting need Python; lcm-spy needs Java (suggested).
set(CPACK_DEBIAN_PACKAGE_DEPENDS "python3")
if(CMAKE_CROSSCOMPILING AND CMAKE_SYSTEM_PROCESSOR STREQUAL "aarch64")
  # The arm64 cross build (preset arm64): CPack would name the build machine's architecture, and
  # dpkg-shlibdeps cannot resolve LCM and GeographicLib, which the toolchain file takes from
  # extracted packages that dpkg does not know (toolchain/setup). The shared libraries magvec and
  # magvecd need are listed instead, with the versions dpkg-shlibdeps gives the amd64 package of
  # the same Debian 12 libraries (the NEEDED entries of the two programs).
  set(CPACK_DEBIAN_PACKAGE_ARCHITECTURE arm64)
  set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS OFF)
  string(CONCAT CPACK_DEBIAN_PACKAGE_DEPENDS
         "python3, libc6 (>= 2.35), libfmt9 (>= 9.1.0+ds1), libgcc-s1 (>= 3.0), "
         "libgeographiclib23 (>= 1.50), libgpiod2 (>= 1.1), liblcm1, libspdlog1.10-fmt9, "
         "libstdc++6 (>= 12), libsystemd0, libtomlplusplus3 (>= 3.2.0)")
endif()
set(CPACK_DEBIAN_PACKAGE_RECOMMENDS "python3-matplotlib, python3-numpy, liblcm-bin")
set(CPACK_DEBIAN_PACKAGE_SUGGESTS "liblcm-java")
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION ON)
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
    ${PROJECT_SOURCE_DIR}/packaging/debian/conffiles ${PROJECT_SOURCE_DIR}/packaging/debian/postinst
    ${PROJECT_SOURCE_DIR}/packaging/debian/prerm ${PROJECT_SOURCE_DIR}/packaging/debian/postrm)
include(CPack)

# Debian's per-package documentation: the copyright file and the changelog (gzip -9n: no time stamp,
# so the package is reproducible).
include(GNUInstallDirs)
set(_magvec_changelog_gz ${PROJECT_BINARY_DIR}/packaging/changelog.gz)
file(MAKE_DIRECTORY ${PROJECT_BINARY_DIR}/packaging)
execute_process(COMMAND gzip -9n -c ${PROJECT_SOURCE_DIR}/packaging/debian/changelog
                OUTPUT_FILE ${_magvec_changelog_gz} RESULT_VARIABLE _gz_rc)
if(NOT _gz_rc EQUAL 0)
  message(FATAL_ERROR "gzip of packaging/debian/changelog failed")
endif()
install(FILES ${PROJECT_SOURCE_DIR}/packaging/debian/copyright ${_magvec_changelog_gz}
        ${PROJECT_SOURCE_DIR}/README.md
        DESTINATION ${CMAKE_INSTALL_DATADIR}/doc/magvec)

# Manual pages from the programs' own --help (help2man), when it is installed (toolchain/setup).
find_program(HELP2MAN help2man)
if(HELP2MAN)
  set(_man ${PROJECT_BINARY_DIR}/packaging/man)
  file(MAKE_DIRECTORY ${_man})
  foreach(prog_section_name IN ITEMS
          "magvec|1|strapdown magnetometer calibration, replay and reports"
          "magvecd|8|magnetic vector calibration daemon: devices, sensor loop, LCM")
    string(REPLACE "|" ";" _f "${prog_section_name}")
    list(GET _f 0 _prog)
    list(GET _f 1 _sec)
    list(GET _f 2 _what)
    # help2man runs the program: in a cross build (arm64) through a wrapper of the same name that
    # runs it under the emulator (qemu-user), so binfmt_misc need not be registered.
    set(_run $<TARGET_FILE:${_prog}>)
    if(CMAKE_CROSSCOMPILING_EMULATOR)
      list(JOIN CMAKE_CROSSCOMPILING_EMULATOR " " _emu)
      set(_run ${_man}/run/${_prog})
      file(GENERATE OUTPUT ${_run}
           CONTENT "#!/bin/sh\nexec ${_emu} $<TARGET_FILE:${_prog}> \"$@\"\n"
           FILE_PERMISSIONS OWNER_READ OWNER_WRITE OWNER_EXECUTE GROUP_READ GROUP_EXECUTE
                            WORLD_READ WORLD_EXECUTE)
    endif()
    add_custom_command(
      OUTPUT ${_man}/${_prog}.${_sec}.gz
      COMMAND ${HELP2MAN} --no-info --no-discard-stderr --section=${_sec}
              --version-string=${PROJECT_VERSION} "--name=${_what}"
              --output=${_man}/${_prog}.${_sec} ${_run}
      COMMAND gzip -9nf ${_man}/${_prog}.${_sec}
      DEPENDS ${_prog}
      COMMENT "help2man: ${_prog}.${_sec}"
      VERBATIM)
    add_custom_target(${_prog}_man ALL DEPENDS ${_man}/${_prog}.${_sec}.gz)
    install(FILES ${_man}/${_prog}.${_sec}.gz DESTINATION ${CMAKE_INSTALL_MANDIR}/man${_sec})
  endforeach()
endif()
