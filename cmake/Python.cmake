# The Python module (python/pillarseg: pure Python over the C API through ctypes), installed by
# `cmake --install` into PREFIX/PILLARSEG_PYTHON_INSTALL_DIR beside the library, with
# _installed.py saying where the library lies relative to the package (python/pillarseg/_capi.py
# reads it). The default directory is Python's own purelib relative to its prefix: on Debian
# lib/python3.X/dist-packages, which Debian's python3 reads under /usr/local.
find_package(Python3 COMPONENTS Interpreter)
set(pillarseg_python_dir_default lib/python3/dist-packages)
if(Python3_Interpreter_FOUND)
  execute_process(
    COMMAND ${Python3_EXECUTABLE} -c
            "import os, sysconfig; print(os.path.relpath(sysconfig.get_path('purelib'), sysconfig.get_path('data')))"
    OUTPUT_VARIABLE pillarseg_python_purelib OUTPUT_STRIP_TRAILING_WHITESPACE RESULT_VARIABLE pillarseg_python_status)
  if(pillarseg_python_status EQUAL 0 AND NOT pillarseg_python_purelib MATCHES "^\\.\\.")
    set(pillarseg_python_dir_default ${pillarseg_python_purelib})
  endif()
endif()
set(PILLARSEG_PYTHON_INSTALL_DIR ${pillarseg_python_dir_default} CACHE STRING
    "Where `cmake --install` puts the Python package, relative to the prefix")
if(IS_ABSOLUTE "${PILLARSEG_PYTHON_INSTALL_DIR}")
  message(FATAL_ERROR "PILLARSEG_PYTHON_INSTALL_DIR must be relative to the install prefix, got "
                      "${PILLARSEG_PYTHON_INSTALL_DIR}")
endif()

if(IS_ABSOLUTE "${CMAKE_INSTALL_LIBDIR}")
  set(pillarseg_library_from_package ${CMAKE_INSTALL_LIBDIR})
else()
  file(RELATIVE_PATH pillarseg_library_from_package "/prefix/${PILLARSEG_PYTHON_INSTALL_DIR}/pillarseg"
       "/prefix/${CMAKE_INSTALL_LIBDIR}")
  string(REGEX REPLACE "/$" "" pillarseg_library_from_package "${pillarseg_library_from_package}")
endif()
file(GENERATE OUTPUT ${PROJECT_BINARY_DIR}/python/_installed.py CONTENT
"# Written by CMake for `cmake --install`: the library beside this package, relative to it.
LIBRARY = \"${pillarseg_library_from_package}/$<TARGET_SONAME_FILE_NAME:pillarseg_shared>\"
")
install(DIRECTORY ${PROJECT_SOURCE_DIR}/python/pillarseg DESTINATION ${PILLARSEG_PYTHON_INSTALL_DIR}
        FILES_MATCHING PATTERN "*.py" PATTERN "__pycache__" EXCLUDE)
install(FILES ${PROJECT_BINARY_DIR}/python/_installed.py DESTINATION ${PILLARSEG_PYTHON_INSTALL_DIR}/pillarseg)
