# aarch64 (arm64) Linux, the SBC class magvecd targets (Cortex-A53/A72/A76): Debian's cross
# toolchain (g++-aarch64-linux-gnu) against the arm64 multiarch libraries of the build machine
# (dpkg --add-architecture arm64; toolchain/setup installs them). Programs and tests run under
# qemu-user (qemu-aarch64, CMAKE_CROSSCOMPILING_EMULATOR): ctest, gtest_discover_tests and the
# custom commands that run a built program use it, so binfmt_misc need not be registered. The
# aarch64 dynamic loader is libc6:arm64's /lib/ld-linux-aarch64.so.1, and the libraries are found
# in /usr/lib/aarch64-linux-gnu (ld.so.conf.d/aarch64-linux-gnu.conf).
#
# LCM and GeographicLib have no co-installable arm64 -dev package (liblcm-dev, liblcm-bin and
# libgeographiclib-dev are not Multi-Arch: same), so toolchain/setup extracts their arm64 packages
# into MAGVEC_ARM64_SYSROOT (default /opt/magvec-arm64) with the pkg-config files pointing there;
# the build tree's RPATH names that directory, the installed programs (and the Debian package,
# which depends on liblcm1 and libgeographiclib23) do not. Build-time generators run on the host:
# lcm-gen is the amd64 one (liblcm-bin), found through PATH.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)

if(NOT MAGVEC_ARM64_SYSROOT)
  set(MAGVEC_ARM64_SYSROOT /opt/magvec-arm64)
endif()
set(MAGVEC_ARM64_SYSROOT ${MAGVEC_ARM64_SYSROOT} CACHE PATH
    "Extracted arm64 packages that do not co-install with their amd64 versions (LCM, GeographicLib)")

find_program(MAGVEC_QEMU_AARCH64 qemu-aarch64 REQUIRED)
set(CMAKE_CROSSCOMPILING_EMULATOR ${MAGVEC_QEMU_AARCH64})

# pkg-config: only the arm64 .pc files (multiarch and the extracted ones) and the
# architecture-independent ones, never the amd64 directory.
set(ENV{PKG_CONFIG_LIBDIR}
    "/usr/lib/aarch64-linux-gnu/pkgconfig:${MAGVEC_ARM64_SYSROOT}/usr/lib/aarch64-linux-gnu/pkgconfig:/usr/share/pkgconfig")
set(ENV{PKG_CONFIG_PATH} "")

# Headers and libraries of the build machine's root (multiarch) plus the extracted packages;
# programs (lcm-gen, javac, help2man, qemu) are the host's.
set(CMAKE_FIND_ROOT_PATH / ${MAGVEC_ARM64_SYSROOT})
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
