# The library users link: the C API of include/pillarseg/ (engine/api/c_api.cpp) over every layer,
#   pillarseg_shared  libpillarseg.so, exporting the pillarseg_* functions alone (a version
#                     script), with its dependencies linked in or as shared libraries;
#   pillarseg_static  libpillarseg.a, every layer's objects in one archive (its users also link
#                     its dependencies: the CMake package's "static" component finds them);
# installed by `cmake --install` with the headers, a CMake package (find_package(pillarseg
# CONFIG) -> pillarseg::pillarseg, pillarseg::pillarseg_static) and a pkg-config file, beside the
# command line.
include(GNUInstallDirs)
include(CMakePackageConfigHelpers)

add_library(pillarseg_api OBJECT ${PROJECT_SOURCE_DIR}/engine/api/c_api.cpp)
target_include_directories(pillarseg_api PUBLIC $<BUILD_INTERFACE:${PROJECT_SOURCE_DIR}/include>)
target_compile_definitions(pillarseg_api PRIVATE PILLARSEG_VERSION_STRING="${PROJECT_VERSION}")
target_link_libraries(pillarseg_api PRIVATE pillarseg_engine)
if(TARGET pillarseg_cuda_backend)
  target_compile_definitions(pillarseg_api PRIVATE PILLARSEG_WITH_CUDA_BACKEND)
endif()
pillarseg_set_warnings(pillarseg_api)
pillarseg_set_arch(pillarseg_api)

# The layers in the library, bottom up; the CUDA backends linked without their usage requirements
# (the emulated build's PILLARSEG_CUDA_EMULATION must not reach the API's source).
set(PILLARSEG_LIBRARY_PARTS pillarseg_core pillarseg_host pillarseg_weights_io pillarseg_engine
                            pillarseg_kernels_emu pillarseg_cuda_backend_emu)
if(TARGET pillarseg_cuda_backend)
  list(APPEND PILLARSEG_LIBRARY_PARTS pillarseg_kernels_cuda pillarseg_vendor_conv
                                      pillarseg_cuda_backend)
endif()

add_library(pillarseg_shared SHARED $<TARGET_OBJECTS:pillarseg_api>)
set_target_properties(pillarseg_shared PROPERTIES
  OUTPUT_NAME pillarseg EXPORT_NAME pillarseg
  VERSION ${PROJECT_VERSION} SOVERSION ${PROJECT_VERSION_MAJOR}
  LINK_DEPENDS ${PROJECT_SOURCE_DIR}/engine/api/exports.map)
target_include_directories(pillarseg_shared INTERFACE
  $<BUILD_INTERFACE:${PROJECT_SOURCE_DIR}/include> $<INSTALL_INTERFACE:${CMAKE_INSTALL_INCLUDEDIR}>)
foreach(part ${PILLARSEG_LIBRARY_PARTS})
  target_link_libraries(pillarseg_shared PRIVATE $<LINK_ONLY:${part}>)
endforeach()
target_link_options(pillarseg_shared PRIVATE
  -Wl,--version-script=${PROJECT_SOURCE_DIR}/engine/api/exports.map -Wl,--no-undefined)
pillarseg_set_warnings(pillarseg_shared)  # with PILLARSEG_SANITIZE, links the sanitizers' runtimes

set(PILLARSEG_STATIC_OBJECTS $<TARGET_OBJECTS:pillarseg_api>)
foreach(part ${PILLARSEG_LIBRARY_PARTS})
  list(APPEND PILLARSEG_STATIC_OBJECTS $<TARGET_OBJECTS:${part}>)
endforeach()
add_library(pillarseg_static STATIC ${PILLARSEG_STATIC_OBJECTS})
set_target_properties(pillarseg_static PROPERTIES OUTPUT_NAME pillarseg EXPORT_NAME pillarseg_static)
target_include_directories(pillarseg_static INTERFACE
  $<BUILD_INTERFACE:${PROJECT_SOURCE_DIR}/include> $<INSTALL_INTERFACE:${CMAKE_INSTALL_INCLUDEDIR}>)
target_link_libraries(pillarseg_static INTERFACE yaml-cpp spdlog::spdlog fmt::fmt PNG::PNG
                                                 OpenMP::OpenMP_CXX Threads::Threads)
set(PILLARSEG_PC_PRIVATE_LIBS "-lyaml-cpp -lspdlog -lfmt -lpng -lgomp -lpthread")
set(PILLARSEG_PACKAGE_CUDA OFF)
if(TARGET pillarseg_cuda_backend)
  find_package(CUDAToolkit REQUIRED)  # its CUDA:: targets are directory-scoped
  target_link_libraries(pillarseg_static INTERFACE CUDA::cudart CUDA::cublas)
  string(APPEND PILLARSEG_PC_PRIVATE_LIBS " -L${CUDAToolkit_LIBRARY_DIR} -lcudart -lcublas")
  if(PILLARSEG_CUDNN_LIBRARY)
    target_link_libraries(pillarseg_static INTERFACE ${PILLARSEG_CUDNN_LIBRARY})
    string(APPEND PILLARSEG_PC_PRIVATE_LIBS " -lcudnn")
  endif()
  set(PILLARSEG_PACKAGE_CUDA ON)
endif()

install(TARGETS pillarseg_shared pillarseg_static EXPORT pillarsegTargets
        LIBRARY DESTINATION ${CMAKE_INSTALL_LIBDIR}
        ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR})
install(TARGETS pillarseg RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})
install(DIRECTORY ${PROJECT_SOURCE_DIR}/include/pillarseg DESTINATION ${CMAKE_INSTALL_INCLUDEDIR})
install(EXPORT pillarsegTargets NAMESPACE pillarseg::
        DESTINATION ${CMAKE_INSTALL_LIBDIR}/cmake/pillarseg)
configure_package_config_file(${PROJECT_SOURCE_DIR}/cmake/pillarsegConfig.cmake.in
                              ${PROJECT_BINARY_DIR}/pillarsegConfig.cmake
                              INSTALL_DESTINATION ${CMAKE_INSTALL_LIBDIR}/cmake/pillarseg)
write_basic_package_version_file(${PROJECT_BINARY_DIR}/pillarsegConfigVersion.cmake
                                 COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/pillarsegConfig.cmake ${PROJECT_BINARY_DIR}/pillarsegConfigVersion.cmake
        DESTINATION ${CMAKE_INSTALL_LIBDIR}/cmake/pillarseg)
configure_file(${PROJECT_SOURCE_DIR}/cmake/pillarseg.pc.in ${PROJECT_BINARY_DIR}/pillarseg.pc @ONLY)
install(FILES ${PROJECT_BINARY_DIR}/pillarseg.pc DESTINATION ${CMAKE_INSTALL_LIBDIR}/pkgconfig)
