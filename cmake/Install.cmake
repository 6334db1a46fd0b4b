# What `cmake --install` and the .deb put where (GNUInstallDirs), and the package (CPack's DEB
# generator). The paths that depend on the prefix chosen at install time (the configuration in
# /etc, the systemd unit, the Python module) are installed by cmake/InstallLayout.cmake.
include(GNUInstallDirs)
# `cmake --install` and CPack install what is built, without building every target first (the
# package's build makes only gs360_installables, not the tests and benchmarks).
set(CMAKE_SKIP_INSTALL_ALL_DEPENDENCY ON)

install(TARGETS gs360 gs360d RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})
install(FILES README.md DESTINATION ${CMAKE_INSTALL_DOCDIR})
install(DIRECTORY docs/ DESTINATION ${CMAKE_INSTALL_DOCDIR})

# Man pages from each program's --help, made once the program is built.
set(gs360_man_dir ${PROJECT_BINARY_DIR}/man)
add_custom_command(
  OUTPUT ${gs360_man_dir}/gs360.1.gz ${gs360_man_dir}/gs360d.1.gz
  COMMAND ${CMAKE_COMMAND} -DEXE=$<TARGET_FILE:gs360> -DNAME=gs360 -DVERSION=${PROJECT_VERSION}
          "-DSUMMARY=controller and calibration for a GelSight360 calibration rig"
          "-DSEE_ALSO=gs360d(1); each command's own --help; /usr/share/doc/gs360/cli.md"
          -DOUT=${gs360_man_dir}/gs360.1.gz -P ${PROJECT_SOURCE_DIR}/cmake/ManPage.cmake
  COMMAND ${CMAKE_COMMAND} -DEXE=$<TARGET_FILE:gs360d> -DNAME=gs360d -DVERSION=${PROJECT_VERSION}
          "-DSUMMARY=the gs360 daemon: runs calibration acquisitions, serves the HTTP API"
          "-DSEE_ALSO=gs360(1); /usr/share/doc/gs360/daemon.md"
          -DOUT=${gs360_man_dir}/gs360d.1.gz -P ${PROJECT_SOURCE_DIR}/cmake/ManPage.cmake
  DEPENDS gs360 gs360d ${PROJECT_SOURCE_DIR}/cmake/ManPage.cmake
  COMMENT "Man pages from --help"
  VERBATIM)
add_custom_target(gs360_man ALL DEPENDS ${gs360_man_dir}/gs360.1.gz ${gs360_man_dir}/gs360d.1.gz)
install(FILES ${gs360_man_dir}/gs360.1.gz ${gs360_man_dir}/gs360d.1.gz
        DESTINATION ${CMAKE_INSTALL_MANDIR}/man1)

# Debian's changelog and copyright, where a package's documentation folder must have them.
add_custom_command(
  OUTPUT ${PROJECT_BINARY_DIR}/packaging/changelog.gz
  COMMAND ${CMAKE_COMMAND} -E make_directory ${PROJECT_BINARY_DIR}/packaging
  COMMAND sh -c "gzip -9nc '${PROJECT_SOURCE_DIR}/packaging/changelog' > '${PROJECT_BINARY_DIR}/packaging/changelog.gz'"
  DEPENDS ${PROJECT_SOURCE_DIR}/packaging/changelog
  VERBATIM)
add_custom_target(gs360_changelog ALL DEPENDS ${PROJECT_BINARY_DIR}/packaging/changelog.gz)
install(FILES ${PROJECT_BINARY_DIR}/packaging/changelog.gz packaging/copyright
        DESTINATION ${CMAKE_INSTALL_DOCDIR})

set(gs360_python_module "")
# Everything the install puts in place, to build only that (scripts/setup.sh package).
add_custom_target(gs360_installables)
add_dependencies(gs360_installables gs360 gs360d gs360_man gs360_changelog)
if(GS360_PYTHON)
  set(gs360_python_module "$<TARGET_FILE:gs360_python>")
  add_dependencies(gs360_installables gs360_python)
endif()
install(CODE "
  set(GS360_SOURCE_DIR \"${PROJECT_SOURCE_DIR}\")
  set(GS360_BINARY_DIR \"${PROJECT_BINARY_DIR}\")
  set(GS360_BINDIR \"${CMAKE_INSTALL_BINDIR}\")
  set(GS360_PYTHON_MODULE \"${gs360_python_module}\")
  set(GS360_PYTHON_VERSION \"${Python3_VERSION_MAJOR}.${Python3_VERSION_MINOR}\")
  include(\"${PROJECT_SOURCE_DIR}/cmake/InstallLayout.cmake\")")

# The .deb: gs360_<version>_<arch>.deb (scripts/setup.sh package). Its library dependencies come
# from the binaries (dpkg-shlibdeps); its maintainer scripts (packaging/deb/) add the system user
# gs360 (in dialout and video, for the machine's port and the camera), its state folder, and
# enable and start the unit the way debhelper would.
set(CPACK_GENERATOR DEB)
set(CPACK_PACKAGE_NAME gs360)
set(CPACK_PACKAGE_VENDOR "the gs360 developers")
set(CPACK_PACKAGE_CONTACT "gs360 maintainers <maintainers@users.noreply.h-seed-e5c45e7d.example>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY "controller and calibration for a GelSight360 tactile sensor rig")
set(CPACK_PACKAGE_DESCRIPTION
    "gs360d streams G-code to a CNC or a 3D printer over serial, presses a\n"
    "ball into an all-around tactile fingertip at thousands of points,\n"
    "captures a camera frame at each press, stores them in SQLite with\n"
    "resume, calibrates, and exports a model that turns tactile images into\n"
    "depth maps. gs360 is its command line, and the Python module gs360 runs\n"
    "an exported model.")
string(JOIN "" CPACK_PACKAGE_DESCRIPTION ${CPACK_PACKAGE_DESCRIPTION})
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)
set(CPACK_DEBIAN_PACKAGE_SECTION science)
set(CPACK_DEBIAN_PACKAGE_PRIORITY optional)
set(CPACK_DEBIAN_PACKAGE_HOMEPAGE "https://h-seed-e5c45e7d.example/gs360")
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)
set(CPACK_DEBIAN_PACKAGE_DEPENDS "adduser")
if(GS360_PYTHON)
  # The module is built for one Python (its ABI tag): that minor version.
  math(EXPR gs360_python_next_minor "${Python3_VERSION_MINOR} + 1")
  set(CPACK_DEBIAN_PACKAGE_RECOMMENDS
      "python3 (>= ${Python3_VERSION_MAJOR}.${Python3_VERSION_MINOR}), python3 (<< ${Python3_VERSION_MAJOR}.${gs360_python_next_minor}), python3-numpy")
endif()
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
    ${PROJECT_SOURCE_DIR}/packaging/deb/conffiles ${PROJECT_SOURCE_DIR}/packaging/deb/postinst
    ${PROJECT_SOURCE_DIR}/packaging/deb/prerm ${PROJECT_SOURCE_DIR}/packaging/deb/postrm)
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION ON)
set(CPACK_STRIP_FILES ON)
include(CPack)
