#pragma once
// Private helper of the fast LSM (src/lsm.cc): projections of image patches onto the 21
// orthonormalised steerable filters, the products the FLSM makes per key point (the 7 design
// images of its template patch) and per iteration (the warped base patch). Eigen's float
// products for them were 12 % of a pipeline pair registration's CPU, a third of it packing the
// constant filter bank again at each call (docs/benchmarks.md, "Session 46"). Not installed.

namespace irmosaic::bank {

// out[k * out_stride + r] = sum over i < n of bank[r * n + i] * columns[k * n + i], for r < rows
// and k < K (K = 1 or 7), in float and then widened to double. The order of the sums is fixed:
// 8 lanes, lane l summing i = l, l + 8, ... below n - n % 8 in order; the lanes added as
// ((l0 + l1) + (l2 + l3)) + ((l4 + l5) + (l6 + l7)); then the remaining i in order, summed
// separately and added last. With AVX2 where the CPU has it (src/simd_dispatch.h), SSE2 else,
// and a scalar reference (`ProjectScalar`): all three give identical results.
void Project(const float* bank, int rows, int n, const float* columns, int k, double* out,
             int out_stride);

// Tests: the scalar reference of Project.
void ProjectScalar(const float* bank, int rows, int n, const float* columns, int k, double* out,
                   int out_stride);

}  // namespace irmosaic::bank
