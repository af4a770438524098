# CUDA is optional: with nvcc present the CUDA targets build, without it everything else does.
# -DPILLARSEG_CUDA=OFF skips them even with nvcc (the sanitizer build, which runs the emulation).
option(PILLARSEG_CUDA "Build the CUDA targets when nvcc is found" ON)
include(CheckLanguage)
if(PILLARSEG_CUDA)
  check_language(CUDA)
endif()
if(PILLARSEG_CUDA AND CMAKE_CUDA_COMPILER)
  if(NOT DEFINED CMAKE_CUDA_ARCHITECTURES)
    set(CMAKE_CUDA_ARCHITECTURES 75 80 86 87 89 90)
  endif()
  enable_language(CUDA)
  # CMake before 3.26 knows no C++20 flag for nvcc and then refuses CUDA_STANDARD 20 (for the
  # kernel libraries and for every target holding their objects, such as libpillarseg.a); nvcc 12
  # and later take -std=c++20.
  if(NOT DEFINED CMAKE_CUDA20_STANDARD_COMPILE_OPTION OR CMAKE_CUDA20_STANDARD_COMPILE_OPTION STREQUAL "")
    set(CMAKE_CUDA20_STANDARD_COMPILE_OPTION "-std=c++20")
    set(CMAKE_CUDA20_EXTENSION_COMPILE_OPTION "-std=c++20")
  endif()
  set(CMAKE_CUDA_STANDARD 20)
  set(CMAKE_CUDA_STANDARD_REQUIRED ON)
  set(PILLARSEG_HAVE_CUDA ON)
  message(STATUS "pillarseg: CUDA found (${CMAKE_CUDA_COMPILER}), architectures ${CMAKE_CUDA_ARCHITECTURES}")
else()
  set(PILLARSEG_HAVE_CUDA OFF)
  message(STATUS "pillarseg: no CUDA compiler (or PILLARSEG_CUDA=OFF); CUDA targets are skipped, emulated kernels still build")
endif()
