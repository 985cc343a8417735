# Writes sm_version.h (cmake -P, run at every build by the sm_version target of
# deploy/cmake/CMakeLists.txt): the project version from project(VERSION) and, when the
# source tree is a git checkout, `git describe`. The file is rewritten only when its text
# changes, so an unchanged commit recompiles nothing.
# Inputs: -DSM_VERSION=X.Y.Z -DSM_SOURCE_DIR=... -DSM_OUT=.../sm_version.h
set(desc "")
find_program(SM_GIT git)
if(SM_GIT AND EXISTS "${SM_SOURCE_DIR}/.git")
  # No --dirty: it refreshes the index (a write), and other processes may be committing
  # in this working tree at the same moment. GIT_OPTIONAL_LOCKS=0 for the same reason.
  set(ENV{GIT_OPTIONAL_LOCKS} 0)
  execute_process(COMMAND "${SM_GIT}" -C "${SM_SOURCE_DIR}" describe --tags --always
                  OUTPUT_VARIABLE desc OUTPUT_STRIP_TRAILING_WHITESPACE
                  RESULT_VARIABLE rc ERROR_QUIET)
  if(NOT rc EQUAL 0)
    set(desc "")
  endif()
endif()
set(text "/* sm_version.h: generated at build time by deploy/cmake/sm_version.cmake. */
#ifndef SM_VERSION_H
#define SM_VERSION_H
#define SM_VERSION \"${SM_VERSION}\"     /* CMake project(VERSION) */
#define SM_VERSION_GIT \"${desc}\"       /* git describe of the build, \"\" outside git */
/* The --version line of both programs: \"PROG 0.1.0 (git DESCRIBE)\". Needs <stdio.h>. */
#define SM_VERSION_PRINT(f, prog)                                                  \\
  fprintf((f), \"%s %s%s%s%s\\n\", (prog), SM_VERSION, SM_VERSION_GIT[0] ? \" (git \" : \"\", \\
          SM_VERSION_GIT, SM_VERSION_GIT[0] ? \")\" : \"\")
#endif
")
set(old "")
if(EXISTS "${SM_OUT}")
  file(READ "${SM_OUT}" old)
endif()
if(NOT old STREQUAL text)
  file(WRITE "${SM_OUT}" "${text}")
endif()
