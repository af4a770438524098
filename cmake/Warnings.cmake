function(pillarseg_set_warnings target)
  target_compile_options(${target} PRIVATE $<$<COMPILE_LANGUAGE:CXX>:-Wall -Wextra -Wpedantic
                         -Wshadow -Wnon-virtual-dtor -Wcast-align -Woverloaded-virtual
                         -Wno-unknown-pragmas
                         # GCC 12 reports false positives inside Eigen's AVX-512 code paths.
                         -Wno-maybe-uninitialized>)
  if(PILLARSEG_WERROR)
    target_compile_options(${target} PRIVATE $<$<COMPILE_LANGUAGE:CXX>:-Werror>)
  endif()
  if(PILLARSEG_SANITIZE)
    target_compile_options(${target} PRIVATE -fsanitize=address,undefined -fno-omit-frame-pointer
                           -fno-sanitize-recover=undefined)
    target_link_options(${target} PRIVATE -fsanitize=address,undefined)
  endif()
endfunction()

function(pillarseg_set_arch target)
  if(PILLARSEG_ARCH)
    target_compile_options(${target} PRIVATE $<$<COMPILE_LANGUAGE:CXX>:-march=${PILLARSEG_ARCH}>)
  endif()
endfunction()
