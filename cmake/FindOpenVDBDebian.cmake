# Debian ships FindOpenVDB.cmake in the multiarch cmake/OpenVDB folder, which is not on any default
# search path. This module adds that folder and then finds OpenVDB (which needs boost-iostreams).
find_path(VISPACK_OPENVDB_MODULE_DIR FindOpenVDB.cmake
  PATHS /usr/lib/${CMAKE_LIBRARY_ARCHITECTURE}/cmake/OpenVDB /usr/lib/cmake/OpenVDB
        /usr/local/lib/cmake/OpenVDB /usr/share/OpenVDB/cmake NO_DEFAULT_PATH)
if(VISPACK_OPENVDB_MODULE_DIR)
  list(APPEND CMAKE_MODULE_PATH ${VISPACK_OPENVDB_MODULE_DIR})
endif()
find_package(OpenVDB ${OpenVDBDebian_FIND_VERSION} REQUIRED)
set(OpenVDBDebian_FOUND ${OpenVDB_FOUND})
