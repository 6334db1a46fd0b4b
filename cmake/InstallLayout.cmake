cmake_minimum_required(VERSION 3.25)
# Run by `cmake --install` (and CPack) after the binaries are in place: installs what needs a path
# that depends on the install prefix, chosen when installing (CPack installs with the prefix /usr
# whatever the build was configured with):
#   prefix /usr (the .deb):  /etc/gs360/gs360d.toml, /lib/systemd/system/gs360d.service,
#                            /usr/lib/python3/dist-packages/gs360*.so
#   any other prefix P:      P/etc/gs360/..., P/lib/systemd/system/..., P/lib/python3.X/dist-packages
#                            (Debian's python3 reads /usr/local/lib/python3.X/dist-packages)
# Inputs (set by install(CODE) in cmake/Install.cmake): GS360_SOURCE_DIR, GS360_BINARY_DIR,
# GS360_BINDIR (relative), GS360_PYTHON_MODULE (empty: no module), GS360_PYTHON_VERSION (3.X).
set(prefix "${CMAKE_INSTALL_PREFIX}")
if(prefix STREQUAL "/usr")
  set(sysconfdir "/etc")
  set(unitdir "/lib/systemd/system")
  set(pythondir "/usr/lib/python3/dist-packages")
else()
  set(sysconfdir "${prefix}/etc")
  set(unitdir "${prefix}/lib/systemd/system")
  set(pythondir "${prefix}/lib/python${GS360_PYTHON_VERSION}/dist-packages")
endif()

set(GS360_BINDIR_FULL "${prefix}/${GS360_BINDIR}")
set(GS360_CONFIG_FILE "${sysconfdir}/gs360/gs360d.toml")
set(unit "${GS360_BINARY_DIR}/packaging/gs360d.service")
configure_file("${GS360_SOURCE_DIR}/packaging/gs360d.service.in" "${unit}" @ONLY)

file(INSTALL "${GS360_SOURCE_DIR}/packaging/gs360d.toml" DESTINATION "${sysconfdir}/gs360"
     PERMISSIONS OWNER_READ OWNER_WRITE GROUP_READ WORLD_READ)
file(INSTALL "${unit}" DESTINATION "${unitdir}"
     PERMISSIONS OWNER_READ OWNER_WRITE GROUP_READ WORLD_READ)
if(GS360_PYTHON_MODULE)
  file(INSTALL "${GS360_PYTHON_MODULE}" DESTINATION "${pythondir}"
       PERMISSIONS OWNER_READ OWNER_WRITE GROUP_READ WORLD_READ)
endif()
