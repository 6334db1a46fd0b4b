# Finds gs360's dependencies and records what was found for the configure summary.
# Core (required): Eigen, spdlog, SQLite, OpenCV, assimp, nlohmann-json, CLI11, Catch2 (tests),
# toml++, cpp-httplib and libsystemd (the daemon).
# Optional backends: libcamera (capture), libserialport (real serial ports).

find_package(PkgConfig REQUIRED)
find_package(Threads REQUIRED)

set(GS360_FOUND_SUMMARY "")
macro(gs360_note name status)
  list(APPEND GS360_FOUND_SUMMARY "${name}|${status}")
endmacro()

find_package(Eigen3 3.3 REQUIRED NO_MODULE)
gs360_note("Eigen" "${Eigen3_VERSION}")
find_package(spdlog REQUIRED)
gs360_note("spdlog" "${spdlog_VERSION}")
find_package(SQLite3 REQUIRED)
gs360_note("SQLite" "${SQLite3_VERSION}")
find_package(OpenCV 4 REQUIRED COMPONENTS core imgproc imgcodecs calib3d videoio dnn)
gs360_note("OpenCV" "${OpenCV_VERSION}")
find_package(assimp REQUIRED)
gs360_note("assimp" "${assimp_VERSION}")
find_package(nlohmann_json 3 REQUIRED)
gs360_note("nlohmann-json" "${nlohmann_json_VERSION}")
find_package(CLI11 REQUIRED)
gs360_note("CLI11" "${CLI11_VERSION}")

# The daemon: its configuration file, HTTP server, systemd notifications.
find_package(tomlplusplus 3 REQUIRED)
gs360_note("toml++" "${tomlplusplus_VERSION}")
pkg_check_modules(HTTPLIB REQUIRED IMPORTED_TARGET cpp-httplib)
gs360_note("cpp-httplib" "${HTTPLIB_VERSION}")
# gs360d's server: event-driven, so that idle, slow and streaming clients take no thread
# (cpp-httplib, kept for the clients, gives each connection a thread: docs/daemon.md).
pkg_check_modules(MHD REQUIRED IMPORTED_TARGET libmicrohttpd)
gs360_note("libmicrohttpd" "${MHD_VERSION}")
pkg_check_modules(SYSTEMD REQUIRED IMPORTED_TARGET libsystemd)
gs360_note("libsystemd" "${SYSTEMD_VERSION}")

# FFTW3 (double): the DST-I behind the Poisson solver (recon/).
pkg_check_modules(FFTW3 REQUIRED IMPORTED_TARGET fftw3)
gs360_note("FFTW3" "${FFTW3_VERSION}")
# ONNX export (calib/): Debian's libonnx-dev, whose targets carry ONNX_ML=1 and
# ONNX_NAMESPACE=onnx and pull in protobuf.
find_package(Protobuf REQUIRED)
find_package(ONNX REQUIRED)
gs360_note("ONNX" "libonnx (protobuf ${Protobuf_VERSION})")

pkg_check_modules(SERIALPORT IMPORTED_TARGET libserialport)
if(SERIALPORT_FOUND)
  gs360_note("libserialport" "${SERIALPORT_VERSION}")
else()
  gs360_note("libserialport" "not found: real serial ports unavailable (pty and tcp still work)")
endif()

set(GS360_HAVE_LIBCAMERA OFF)
if(GS360_WITH_LIBCAMERA)
  pkg_check_modules(LIBCAMERA IMPORTED_TARGET libcamera)
  if(LIBCAMERA_FOUND)
    set(GS360_HAVE_LIBCAMERA ON)
    gs360_note("libcamera" "${LIBCAMERA_VERSION}: backend enabled")
  else()
    gs360_note("libcamera" "not found: backend disabled")
  endif()
else()
  gs360_note("libcamera" "disabled by GS360_WITH_LIBCAMERA=OFF")
endif()

if(GS360_BUILD_TESTS)
  find_package(Catch2 2 REQUIRED)
  include(Catch)
  gs360_note("Catch2" "${Catch2_VERSION}")
endif()

function(gs360_print_summary)
  message(STATUS "")
  message(STATUS "gs360 ${PROJECT_VERSION} configuration (${CMAKE_BUILD_TYPE}, ${CMAKE_CXX_COMPILER_ID} ${CMAKE_CXX_COMPILER_VERSION})")
  foreach(entry ${GS360_FOUND_SUMMARY})
    string(REPLACE "|" ";" parts "${entry}")
    list(GET parts 0 name)
    list(GET parts 1 status)
    string(LENGTH "${name}" len)
    math(EXPR pad "16 - ${len}")
    string(REPEAT " " ${pad} spaces)
    message(STATUS "  ${name}${spaces}${status}")
  endforeach()
  message(STATUS "")
endfunction()
