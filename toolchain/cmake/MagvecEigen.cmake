# Eigen 3.4 (Debian libeigen3-dev). Cross builds use the same headers: Eigen is header-only, and
# the firmware core includes only fixed-size types (EIGEN_NO_MALLOC turns any heap use into an error).
if(NOT TARGET Eigen3::Eigen)
  if(NOT CMAKE_CROSSCOMPILING)
    find_package(Eigen3 3.4 QUIET NO_MODULE)
  endif()
  if(NOT TARGET Eigen3::Eigen)
    find_path(MAGVEC_EIGEN_INCLUDE_DIR Eigen/Core
              PATHS /usr/include/eigen3 /usr/local/include/eigen3 NO_CMAKE_FIND_ROOT_PATH REQUIRED)
    add_library(Eigen3::Eigen INTERFACE IMPORTED)
    set_target_properties(Eigen3::Eigen PROPERTIES
      INTERFACE_INCLUDE_DIRECTORIES ${MAGVEC_EIGEN_INCLUDE_DIR}
      INTERFACE_SYSTEM_INCLUDE_DIRECTORIES ${MAGVEC_EIGEN_INCLUDE_DIR})
  endif()
endif()
