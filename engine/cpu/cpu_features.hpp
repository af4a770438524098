// Which of the CPU backend's own 16-bit and INT8 kernels this CPU, its OS and this build run,
// asked at run time: AVX512_BF16, AVX512-VNNI and AVX512BW (libgcc's CPU model), AMX-BF16 and AMX-INT8
// (CPUID, the tile state in XCR0, and Linux's grant of it to this process), and the fastest
// kernels of each family (PILLARSEG_CPU_AMX=0 keeps to AVX-512, to compare). The kernels
// themselves: bf16_conv.hpp and int8_conv.hpp.
#pragma once

#include <string>

namespace pillarseg::cpu {

enum class Bf16Kernels { Avx512, Emulated, Amx, AmxEmulated };

// Whether this CPU and its OS run the AVX512_BF16 micro-kernel (AVX512F, BW, VL and BF16, and
// this build has it); else false with what is missing in why_not.
bool avx512_bf16_available(std::string* why_not = nullptr);
// Whether the AMX path runs here: AVX512_BF16 as above, AMX-TILE and AMX-BF16 (CPUID), the tile
// state enabled by the OS (XCR0) and granted to this process (Linux's arch_prctl
// ARCH_REQ_XCOMP_PERM, asked once); else false with what is missing in why_not.
bool amx_bf16_available(std::string* why_not = nullptr);
// The fastest kernels this CPU runs: Amx where amx_bf16_available (unless PILLARSEG_CPU_AMX=0 is
// in the environment, read on each call: to compare the two paths), else Avx512 (which may
// itself be unavailable: avx512_bf16_available says).
Bf16Kernels native_bf16_kernels();
// "avx512_bf16", "emulated", "amx_bf16" or "amx_bf16 (emulated)".
const char* bf16_kernels_name(Bf16Kernels kernels);
// Whether this CPU's VDPBF16PS issues twice the products of its FP32 FMAs a cycle: AMD's (Zen 4
// and later, CPUID vendor AuthenticAMD), not Intel's cores (one VDPBF16PS a cycle, two FMAs).
bool bf16_dot_outpaces_fma();

// Whether this CPU and its OS run the AVX-512 forms of the 16-bit data movement (half_ops.hpp:
// AVX512F, BW and VL, and this build has them); else false with what is missing in why_not.
bool avx512_half_ops_available(std::string* why_not = nullptr);

enum class Int8Kernels { Vnni, Emulated, Amx, AmxEmulated };

// Whether this CPU and its OS run the VNNI micro-kernel (AVX512F, BW, VL and VNNI, and this build
// has it); else false with what is missing in why_not.
bool avx512_vnni_available(std::string* why_not = nullptr);
// Whether the AMX-INT8 path runs here: VNNI as above, AMX-TILE and AMX-INT8 (CPUID leaf 7 EDX
// bits 24 and 25; AMX-BF16 is bit 22, a separate feature), the tile state enabled by the OS (XCR0
// bits 17 and 18) and granted to this process (Linux's arch_prctl ARCH_REQ_XCOMP_PERM, asked
// once); else false with what is missing in why_not.
bool amx_int8_available(std::string* why_not = nullptr);
// The fastest kernels this CPU runs: Amx where amx_int8_available (unless PILLARSEG_CPU_AMX=0 is
// in the environment, read on each call), else Vnni (which may itself be unavailable:
// avx512_vnni_available says).
Int8Kernels native_int8_kernels();
// "avx512_vnni", "emulated", "amx_int8" or "amx_int8 (emulated)".
const char* int8_kernels_name(Int8Kernels kernels);

// Which INT8 3x3 pad-1 convolutions with calibrated Winograd-domain scales run in that domain on
// the VNNI kernels (int8_conv.hpp, int8_winograd_runs): Pays, those where it is the faster (the
// default); Never or Always, from PILLARSEG_CPU_INT8_WINOGRAD=0 or 1 in the environment (read on
// each call; any other value is an error naming the variable): to compare the two forms.
enum class Int8WinogradRule { Pays, Never, Always };
Int8WinogradRule int8_winograd_rule();

}  // namespace pillarseg::cpu
