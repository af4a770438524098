// The CPU feature checks of cpu_features.hpp.
#include "engine/cpu/cpu_features.hpp"

#if defined(__x86_64__)
#include <cpuid.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <string>
#include <string_view>

#include "core/error.hpp"

namespace pillarseg::cpu {

namespace {

// A check's answer: true where nothing is missing, else false with what is (where asked).
bool answer(const std::string& missing, std::string* why_not) {
  if (missing.empty()) return true;
  if (why_not != nullptr) *why_not = missing;
  return false;
}

#if defined(PILLARSEG_HAVE_AVX512_BF16_KERNELS) || defined(PILLARSEG_HAVE_AVX512_VNNI_KERNELS) || \
    defined(PILLARSEG_HAVE_AVX512_HALF_OPS)
// What AVX-512 lacks for kernels built on AVX512F, BW and VL and one extension (`extension`
// present or not, named `name`; none where name is null): "" where nothing does. libgcc reports
// AVX-512 features only where the OS saves the ZMM registers (XCR0).
std::string avx512_missing(bool extension = true, const char* name = nullptr) {
  __builtin_cpu_init();
  std::string missing;
  const auto need = [&](bool present, const char* feature) {
    if (!present) missing += (missing.empty() ? "" : ", ") + std::string(feature);
  };
  need(__builtin_cpu_supports("avx512f") != 0, "AVX512F");
  need(__builtin_cpu_supports("avx512bw") != 0, "AVX512BW");
  need(__builtin_cpu_supports("avx512vl") != 0, "AVX512VL");
  if (name != nullptr) need(extension, name);
  return missing.empty() ? "" : "this CPU (or its OS) lacks " + missing;
}
#endif

#if (defined(PILLARSEG_HAVE_AMX_BF16_KERNELS) || defined(PILLARSEG_HAVE_AMX_INT8_KERNELS)) && \
    defined(__x86_64__) && defined(__linux__)
// What the AMX tiles with the arithmetic of CPUID.(7, 0):EDX bit `bit` (AMX-BF16 22, AMX-INT8 25)
// lack on this CPU, OS and process: "" where they run. Asks Linux for the tile state.
std::string amx_missing(unsigned bit, const char* name) {
  unsigned eax = 0, ebx = 0, ecx = 0, edx = 0;
  if (__get_cpuid_count(7, 0, &eax, &ebx, &ecx, &edx) == 0) return "this CPU has no CPUID leaf 7";
  std::string missing;
  if (((edx >> 24) & 1u) == 0) missing = "AMX-TILE";
  if (((edx >> bit) & 1u) == 0) missing += (missing.empty() ? "" : ", ") + std::string(name);
  if (!missing.empty()) return "this CPU lacks " + missing;
  unsigned xcr0_lo = 0, xcr0_hi = 0;
  __asm__ volatile("xgetbv" : "=a"(xcr0_lo), "=d"(xcr0_hi) : "c"(0));  // OSXSAVE: AVX-512 above
  if (((xcr0_lo >> 17) & 3u) != 3u)
    return "the OS does not enable the AMX tile state (XCR0 bits 17, 18)";
  constexpr long kArchReqXcompPerm = 0x1023, kXfeatureXtiledata = 18;  // <asm/prctl.h>
  if (::syscall(SYS_arch_prctl, kArchReqXcompPerm, kXfeatureXtiledata) != 0) {
    return std::string(
               "Linux did not grant this process the AMX tile state (arch_prctl "
               "ARCH_REQ_XCOMP_PERM: ") +
           std::strerror(errno) + "; Linux 5.16 or later grants it)";
  }
  return "";
}
#endif

// PILLARSEG_CPU_AMX=0: the AVX-512 kernels even where the AMX tiles run, to compare.
bool amx_switched_off() {
  const char* amx = std::getenv("PILLARSEG_CPU_AMX");
  return amx != nullptr && std::string_view(amx) == "0";
}

// The AMX-BF16 check's answer, worked out once.
std::string amx_bf16_missing() {
  std::string why;
  if (!avx512_bf16_available(&why)) return why;
#if defined(PILLARSEG_HAVE_AMX_BF16_KERNELS) && defined(__x86_64__) && defined(__linux__)
  return amx_missing(22, "AMX-BF16");
#else
  return "this build has no AMX-BF16 tiles (not x86-64 Linux, or the compiler lacks -mamx-bf16)";
#endif
}

// The AMX-INT8 check's answer, worked out once.
std::string amx_int8_missing() {
  std::string why;
  if (!avx512_vnni_available(&why)) return why;
#if defined(PILLARSEG_HAVE_AMX_INT8_KERNELS) && defined(__x86_64__) && defined(__linux__)
  return amx_missing(25, "AMX-INT8");
#else
  return "this build has no AMX-INT8 tiles (not x86-64 Linux, or the compiler lacks -mamx-int8)";
#endif
}

}  // namespace

bool avx512_bf16_available(std::string* why_not) {
#if defined(PILLARSEG_HAVE_AVX512_BF16_KERNELS)
  return answer(avx512_missing(__builtin_cpu_supports("avx512bf16") != 0, "AVX512_BF16"), why_not);
#else
  return answer(
      "this build has no AVX512_BF16 micro-kernel (not an x86-64 target, or the compiler lacks "
      "-mavx512bf16)",
      why_not);
#endif
}

bool amx_bf16_available(std::string* why_not) {
  static const std::string missing = amx_bf16_missing();
  return answer(missing, why_not);
}

Bf16Kernels native_bf16_kernels() {
  if (amx_switched_off()) return Bf16Kernels::Avx512;
  return amx_bf16_available() ? Bf16Kernels::Amx : Bf16Kernels::Avx512;
}

bool bf16_dot_outpaces_fma() {
#if defined(__x86_64__)
  unsigned eax = 0, vendor[3] = {0, 0, 0};
  if (__get_cpuid(0, &eax, &vendor[0], &vendor[2], &vendor[1]) == 0) return false;
  return std::memcmp(vendor, "AuthenticAMD", 12) == 0;
#else
  return false;
#endif
}

const char* bf16_kernels_name(Bf16Kernels kernels) {
  switch (kernels) {
    case Bf16Kernels::Avx512:
      return "avx512_bf16";
    case Bf16Kernels::Emulated:
      return "emulated";
    case Bf16Kernels::Amx:
      return "amx_bf16";
    case Bf16Kernels::AmxEmulated:
      return "amx_bf16 (emulated)";
  }
  return "?";
}

bool avx512_half_ops_available(std::string* why_not) {
#if defined(PILLARSEG_HAVE_AVX512_HALF_OPS)
  return answer(avx512_missing(), why_not);
#else
  return answer(
      "this build has no AVX-512 16-bit data movement (not an x86-64 target, or the compiler lacks "
      "-mavx512bw)",
      why_not);
#endif
}

bool avx512_vnni_available(std::string* why_not) {
#if defined(PILLARSEG_HAVE_AVX512_VNNI_KERNELS)
  return answer(avx512_missing(__builtin_cpu_supports("avx512vnni") != 0, "AVX512_VNNI"), why_not);
#else
  return answer(
      "this build has no AVX512-VNNI micro-kernel (not an x86-64 target, or the compiler lacks "
      "-mavx512vnni)",
      why_not);
#endif
}

bool amx_int8_available(std::string* why_not) {
  static const std::string missing = amx_int8_missing();
  return answer(missing, why_not);
}

Int8Kernels native_int8_kernels() {
  if (amx_switched_off()) return Int8Kernels::Vnni;
  return amx_int8_available() ? Int8Kernels::Amx : Int8Kernels::Vnni;
}

const char* int8_kernels_name(Int8Kernels kernels) {
  switch (kernels) {
    case Int8Kernels::Vnni:
      return "avx512_vnni";
    case Int8Kernels::Emulated:
      return "emulated";
    case Int8Kernels::Amx:
      return "amx_int8";
    case Int8Kernels::AmxEmulated:
      return "amx_int8 (emulated)";
  }
  return "?";
}

Int8WinogradRule int8_winograd_rule() {
  const char* value = std::getenv("PILLARSEG_CPU_INT8_WINOGRAD");
  if (value == nullptr || *value == '\0') return Int8WinogradRule::Pays;
  const std::string_view v(value);
  if (v == "0") return Int8WinogradRule::Never;
  if (v == "1") return Int8WinogradRule::Always;
  PS_CHECK(false, "PILLARSEG_CPU_INT8_WINOGRAD must be 0 (the direct INT8 kernel for every convolution) or 1 "
           "(the Winograd domain for every 3x3 pad-1 convolution calibrated for it), got '{}'", v);
  return Int8WinogradRule::Pays;
}

}  // namespace pillarseg::cpu
