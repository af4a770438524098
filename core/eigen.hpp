// The one include of Eigen (dense matrices, LU inverses, geometry) for every layer.
// - Eigen never threads a GEMM itself here: its blocking would then depend on the thread count,
//   and so would the results; the ops parallelise over fixed tiles instead (host/conv2d.cpp). The
//   build defines EIGEN_DONT_PARALLELIZE for every target; this header makes sure of it.
// - GCC 12 reports false (maybe-)uninitialized values inside its own AVX-512 intrinsics
//   (_mm512_undefined_ps) when Eigen vectorises for AVX-512 (GCC bug 105593, fixed in GCC 13);
//   the warnings are silenced for Eigen's headers only.
#pragma once

#ifndef EIGEN_DONT_PARALLELIZE
#define EIGEN_DONT_PARALLELIZE
#endif

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/LU>
#pragma GCC diagnostic pop
