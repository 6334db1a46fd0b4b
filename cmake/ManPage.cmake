cmake_minimum_required(VERSION 3.25)
# cmake -DEXE=<program> -DNAME=<name> -DSUMMARY=<one line> -DVERSION=<x.y.z> -DOUT=<name.1.gz>
#       [-DSEE_ALSO=<text>] -P ManPage.cmake
# A man page made of the program's own --help (so it cannot drift from it), gzipped without a
# timestamp (gzip -n) as Debian wants manual pages.
execute_process(COMMAND "${EXE}" --help OUTPUT_VARIABLE help RESULT_VARIABLE rc)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "${EXE} --help failed (${rc})")
endif()
# roff: a backslash is an escape, and a line starting with '.' or ' is a request.
string(REPLACE "\\" "\\e" help "${help}")
string(REGEX REPLACE "(^|\n)([.'])" "\\1\\\\&\\2" help "${help}")
string(REPLACE "-" "\\-" summary "${SUMMARY}")
string(TOUPPER "${NAME}" upper)
# The usage line names the program as it was run: its build path.
string(REPLACE "${EXE}" "${NAME}" help "${help}")
string(CONCAT page ".TH ${upper} 1 \"\" \"${NAME} ${VERSION}\" \"User Commands\"\n"
       ".SH NAME\n${NAME} \\- ${summary}\n"
       ".SH DESCRIPTION\nThe program's \\fB\\-\\-help\\fR:\n.PP\n.nf\n${help}.fi\n")
if(SEE_ALSO)
  string(APPEND page ".SH SEE ALSO\n${SEE_ALSO}\n")
endif()
get_filename_component(dir "${OUT}" DIRECTORY)
file(MAKE_DIRECTORY "${dir}")
string(REGEX REPLACE "\\.gz$" "" plain "${OUT}")
file(WRITE "${plain}" "${page}")
execute_process(COMMAND gzip -9nf "${plain}" RESULT_VARIABLE rc)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "gzip ${plain} failed (${rc})")
endif()
