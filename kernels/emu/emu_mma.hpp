// The warp-level matrix instructions of the tensor cores for the CUDA emulation, as warp
// collectives with the fragment layouts of the PTX ISA (section 9.7.14.5.8 "Matrix Fragments for
// mma.m16n8k16 with floating point type", and ldmatrix, 9.7.14.5.15), so that a kernel that puts
// an element in the wrong register computes a wrong result here as it would on a GPU:
//
//   mma.sync.aligned.m16n8k16.row.col.f32.{bf16,f16}.{bf16,f16}.f32  D = A B + C, with
//     groupID = lane / 4, t = lane % 4;
//     A (16 x 16, 4 registers of 2 elements, low half first): a0 a1 | a2 a3 | a4 a5 | a6 a7 at
//       row g (a0, a1, a4, a5) or g + 8 (a2, a3, a6, a7), column 2 t + (i & 1), + 8 for i >= 4;
//     B (16 x 8, 2 registers): b0 b1 | b2 b3 at row 2 t + (i & 1), + 8 for i >= 2, column g;
//     C, D (16 x 8 floats): c0..c3 at row g (c0, c1) or g + 8, column 2 t + (i & 1).
//   The emulation forms each element of D as the exact sum of C and the 16 products (exact in
//   double: a product of two 16-bit floats has at most 22 significant bits) rounded once to
//   float. A GPU adds in an order and with internal rounding the ISA does not specify, so results
//   there may differ from these in the last bits of the float accumulator.
//
//   mma.sync.aligned.m16n8k32.row.col.s32.{s8,u8}.s8.s32  D = A B + C (section 9.7.14.5.10
//     "Matrix Fragments for mma.m16n8k32", the same for .s8 and .u8), each register four 8-bit
//     elements, the lowest byte first; A's bytes two's complement (.s8, -128..127) or unsigned
//     (.u8, 0..255: a byte 200 is +200, not -56), B's two's complement:
//     A (16 x 32, 4 registers a0..a3 of elements 4 r .. 4 r + 3): row g (a0, a2) or g + 8 (a1,
//       a3), column 4 t + byte, + 16 for a2 and a3;
//     B (32 x 8, 2 registers): row 4 t + byte, + 16 for b1, column g;
//     C, D (16 x 8 signed 32-bit integers): as the floats of m16n8k16.
//   The emulation forms each element of D exactly, C plus the 32 products, and keeps its low 32
//   bits (two's complement): without .satfinite the instruction wraps.
//
//   cp.async.cg.shared.global [dst], [src], 16, src_size (src_size 16, or 0: 16 zero bytes),
//     cp.async.commit_group, cp.async.wait_group N: per thread; the source is read when the copy
//     is issued, the destination written when its group completes (emu_scheduler.hpp,
//     AsyncCopies), so that reading a stage before its wait fails here as it may on a GPU. Both
//     addresses 16-byte aligned (checked).
//
//   ldmatrix.sync.aligned.m8n8.{x1,x2,x4}{,.trans}.shared.b16: lanes 8 j .. 8 j + 7 give the row
//   addresses of matrix j (x1: lanes 0-7; x2: 0-15; x4: all); register j of lane l receives row
//   l / 4, elements 2 (l % 4) and 2 (l % 4) + 1 of matrix j, or with .trans those of its
//   transpose (rows 2 (l % 4) and 2 (l % 4) + 1 of column l / 4). Rows are 16 bytes, 16-byte
//   aligned (checked).
#pragma once

#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "core/error.hpp"
#include "kernels/emu/emu_scheduler.hpp"

namespace pillarseg::emu {

// 16-bit floats: bfloat16 (8 exponent bits) and IEEE binary16 (5), as bits.
inline float bf16_bits_to_float(std::uint16_t bits) {
  return std::bit_cast<float>(std::uint32_t{bits} << 16);
}

inline float f16_bits_to_float(std::uint16_t h) {
  const std::uint32_t sign = std::uint32_t{h & 0x8000u} << 16;
  const std::uint32_t exponent = (h >> 10) & 0x1Fu, mantissa = h & 0x3FFu;
  if (exponent == 0x1F) return std::bit_cast<float>(sign | 0x7F800000u | (mantissa << 13));
  if (exponent == 0) {
    const float magnitude = std::ldexp(static_cast<float>(mantissa), -24);  // subnormal or zero
    return sign != 0 ? -magnitude : magnitude;
  }
  return std::bit_cast<float>(sign | ((exponent + 112) << 23) | (mantissa << 13));
}

struct MmaLane {
  float d[4];
  std::uint32_t a[4], b[2];
  float c[4];
};

template <float (*ToFloat)(std::uint16_t)>
void mma_m16n8k16(void* const* lanes) {
  count_mma_m16n8k16();  // once per warp instruction: this runs once for the 32 lanes
  double a[16][16], b[16][8], c[16][8];
  for (int lane = 0; lane < 32; ++lane) {
    const MmaLane& l = *static_cast<const MmaLane*>(lanes[lane]);
    const int g = lane / 4, t = lane % 4;
    for (int i = 0; i < 8; ++i) {
      const std::uint16_t bits = static_cast<std::uint16_t>(l.a[i / 2] >> (16 * (i & 1)));
      const int row = g + ((i & 2) != 0 ? 8 : 0), col = 2 * t + (i & 1) + (i >= 4 ? 8 : 0);
      a[row][col] = ToFloat(bits);
    }
    for (int i = 0; i < 4; ++i) {
      const std::uint16_t bits = static_cast<std::uint16_t>(l.b[i / 2] >> (16 * (i & 1)));
      b[2 * t + (i & 1) + (i >= 2 ? 8 : 0)][g] = ToFloat(bits);
    }
    for (int i = 0; i < 4; ++i) c[g + (i >= 2 ? 8 : 0)][2 * t + (i & 1)] = l.c[i];
  }
  for (int lane = 0; lane < 32; ++lane) {
    MmaLane& l = *static_cast<MmaLane*>(lanes[lane]);
    const int g = lane / 4, t = lane % 4;
    for (int i = 0; i < 4; ++i) {
      const int row = g + (i >= 2 ? 8 : 0), col = 2 * t + (i & 1);
      double sum = c[row][col];
      for (int k = 0; k < 16; ++k) sum += a[row][k] * b[k][col];
      l.d[i] = static_cast<float>(sum);
    }
  }
}

inline void mma_m16n8k16_collective(bool bf16, float d[4], const std::uint32_t a[4],
                                    const std::uint32_t b[2], const float c[4]) {
  MmaLane lane;
  std::memcpy(lane.a, a, sizeof lane.a);
  std::memcpy(lane.b, b, sizeof lane.b);
  std::memcpy(lane.c, c, sizeof lane.c);
  warp_matrix(bf16 ? "mma.sync.m16n8k16.bf16" : "mma.sync.m16n8k16.f16", 0xffffffffu, &lane,
              bf16 ? &mma_m16n8k16<bf16_bits_to_float> : &mma_m16n8k16<f16_bits_to_float>);
  std::memcpy(d, lane.d, sizeof lane.d);
}

struct MmaS8Lane {
  std::int32_t d[4];
  std::uint32_t a[4], b[2];
  std::int32_t c[4];
};

template <bool UnsignedA>
void mma_m16n8k32_i8(void* const* lanes) {
  count_mma_m16n8k32();  // once per warp instruction
  std::int64_t a[16][32], b[32][8], c[16][8];
  const auto signed_byte = [](std::uint32_t reg, int byte) {
    return static_cast<std::int64_t>(static_cast<std::int8_t>(reg >> (8 * byte)));
  };
  const auto a_byte = [&](std::uint32_t reg, int byte) {
    if constexpr (UnsignedA)
      return static_cast<std::int64_t>(static_cast<std::uint8_t>(reg >> (8 * byte)));
    else
      return signed_byte(reg, byte);
  };
  for (int lane = 0; lane < 32; ++lane) {
    const MmaS8Lane& l = *static_cast<const MmaS8Lane*>(lanes[lane]);
    const int g = lane / 4, t = lane % 4;
    for (int r = 0; r < 4; ++r)
      for (int byte = 0; byte < 4; ++byte)
        a[g + (r % 2) * 8][4 * t + byte + (r / 2) * 16] = a_byte(l.a[r], byte);
    for (int r = 0; r < 2; ++r)
      for (int byte = 0; byte < 4; ++byte) b[4 * t + byte + r * 16][g] = signed_byte(l.b[r], byte);
    for (int i = 0; i < 4; ++i) c[g + (i >= 2 ? 8 : 0)][2 * t + (i & 1)] = l.c[i];
  }
  for (int lane = 0; lane < 32; ++lane) {
    MmaS8Lane& l = *static_cast<MmaS8Lane*>(lanes[lane]);
    const int g = lane / 4, t = lane % 4;
    for (int i = 0; i < 4; ++i) {
      const int row = g + (i >= 2 ? 8 : 0), col = 2 * t + (i & 1);
      std::int64_t sum = c[row][col];
      for (int k = 0; k < 32; ++k) sum += a[row][k] * b[k][col];
      l.d[i] = static_cast<std::int32_t>(static_cast<std::uint32_t>(sum));  // the low 32 bits
    }
  }
}

// unsigned_a: A's bytes are .u8; otherwise .s8.
inline void mma_m16n8k32_i8_collective(bool unsigned_a, std::int32_t d[4],
                                       const std::uint32_t a[4], const std::uint32_t b[2],
                                       const std::int32_t c[4]) {
  MmaS8Lane lane;
  std::memcpy(lane.a, a, sizeof lane.a);
  std::memcpy(lane.b, b, sizeof lane.b);
  std::memcpy(lane.c, c, sizeof lane.c);
  warp_matrix(unsigned_a ? "mma.sync.m16n8k32.u8.s8" : "mma.sync.m16n8k32.s8.s8", 0xffffffffu,
              &lane, unsigned_a ? &mma_m16n8k32_i8<true> : &mma_m16n8k32_i8<false>);
  std::memcpy(d, lane.d, sizeof lane.d);
}

struct LdmatrixLane {
  const std::uint16_t* row = nullptr;
  std::uint32_t r[4] = {0, 0, 0, 0};
};

template <int Matrices, bool Transposed>
void ldmatrix_compute(void* const* lanes) {
  std::uint16_t m[4][8][8];
  for (int j = 0; j < Matrices; ++j) {
    for (int r = 0; r < 8; ++r) {
      const std::uint16_t* row = static_cast<const LdmatrixLane*>(lanes[8 * j + r])->row;
      PS_CHECK(
          reinterpret_cast<std::uintptr_t>(row) % 16 == 0,
          "CUDA emulation: ldmatrix: lane {} gave the row address {}, which is not 16-byte aligned",
          8 * j + r, static_cast<const void*>(row));
      std::memcpy(m[j][r], row, 16);
    }
  }
  for (int lane = 0; lane < 32; ++lane) {
    LdmatrixLane& l = *static_cast<LdmatrixLane*>(lanes[lane]);
    const int row = lane / 4, col = 2 * (lane % 4);
    for (int j = 0; j < Matrices; ++j) {
      const std::uint16_t lo = Transposed ? m[j][col][row] : m[j][row][col];
      const std::uint16_t hi = Transposed ? m[j][col + 1][row] : m[j][row][col + 1];
      l.r[j] = std::uint32_t{lo} | (std::uint32_t{hi} << 16);
    }
  }
}

template <int Matrices, bool Transposed>
void ldmatrix_collective(std::uint32_t* r, const void* row_address) {
  LdmatrixLane lane;
  lane.row = static_cast<const std::uint16_t*>(row_address);
  warp_matrix(Transposed ? "ldmatrix.trans" : "ldmatrix", 0xffffffffu, &lane,
              &ldmatrix_compute<Matrices, Transposed>);
  for (int j = 0; j < Matrices; ++j) r[j] = lane.r[j];
}

// cp.async of 16 bytes (zeros when !fill), cp.async.commit_group, cp.async.wait_group.
inline void cp_async_16(void* shared_destination, const void* global_source, bool fill) {
  PS_CHECK(
      reinterpret_cast<std::uintptr_t>(shared_destination) % 16 == 0 &&
          reinterpret_cast<std::uintptr_t>(global_source) % 16 == 0,
      "CUDA emulation: cp.async of 16 bytes from {} to {}: both addresses must be 16-byte aligned",
      global_source, shared_destination);
  count_cp_async_bytes(16);
  AsyncCopy copy;
  copy.destination = static_cast<std::byte*>(shared_destination);
  if (fill) std::memcpy(copy.bytes.data(), global_source, 16);
  thread_async_copies().open.push_back(copy);
}

inline void cp_async_commit_group() {
  AsyncCopies& copies = thread_async_copies();
  copies.committed.push_back(std::move(copies.open));
  copies.open.clear();
}

// Completes the committed groups but the `pending` newest.
inline void cp_async_wait_group(int pending) {
  AsyncCopies& copies = thread_async_copies();
  while (copies.committed.size() > static_cast<std::size_t>(pending)) {
    for (const AsyncCopy& copy : copies.committed.front())
      std::memcpy(copy.destination, copy.bytes.data(), 16);
    copies.committed.pop_front();
  }
}

}  // namespace pillarseg::emu
