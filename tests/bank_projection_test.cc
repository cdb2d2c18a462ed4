// The FLSM's filter-bank projections (src/bank_projection.h): the vector paths against the
// scalar reference (identical), and all against the products in double (close).
#include "../src/bank_projection.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "../src/simd_dispatch.h"

namespace irmosaic {
namespace {

struct Case {
  int rows, n, k;
};

TEST(BankProjectionTest, VectorPathsEqualTheScalarReferenceAndTheProductInDouble) {
  std::mt19937 rng(46);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  // The pipeline's sizes (21 filters of 35 x 35 and 23 x 23 patches), sizes with a tail of
  // every length, and a patch smaller than the 8 lanes.
  const std::vector<Case> cases = {{21, 1225, 1}, {21, 1225, 7}, {21, 529, 7},
                                   {21, 1227, 1}, {21, 1231, 7}, {3, 7, 1},
                                   {3, 5, 7},     {5, 8, 7},     {21, 9, 1}};
  for (const Case& c : cases) {
    std::vector<float> bank(static_cast<size_t>(c.rows) * c.n),
        columns(static_cast<size_t>(c.k) * c.n);
    for (float& v : bank) v = normal(rng);
    // Image-like columns: an offset (thermal counts) plus texture.
    for (float& v : columns) v = 3000.0f + 200.0f * normal(rng);
    std::vector<double> reference(static_cast<size_t>(c.rows) * c.k), baseline(reference.size()),
        best(reference.size()), exact(reference.size());
    bank::ProjectScalar(bank.data(), c.rows, c.n, columns.data(), c.k, reference.data(), c.rows);
    const bool allowed = simd::SetAvx2Allowed(false);
    bank::Project(bank.data(), c.rows, c.n, columns.data(), c.k, baseline.data(), c.rows);
    simd::SetAvx2Allowed(allowed);
    bank::Project(bank.data(), c.rows, c.n, columns.data(), c.k, best.data(), c.rows);
    double scale = 0.0, worst = 0.0;
    for (int k = 0; k < c.k; ++k) {
      for (int r = 0; r < c.rows; ++r) {
        double sum = 0.0, magnitude = 0.0;
        for (int i = 0; i < c.n; ++i) {
          const double term = static_cast<double>(bank[static_cast<size_t>(r) * c.n + i]) *
                              columns[static_cast<size_t>(k) * c.n + i];
          sum += term;
          magnitude += std::abs(term);
        }
        const size_t at = static_cast<size_t>(k) * c.rows + r;
        exact[at] = sum;
        scale = std::max(scale, magnitude);
        worst = std::max(worst, std::abs(reference[at] - sum));
        EXPECT_EQ(baseline[at], reference[at]) << c.rows << " x " << c.n << " k " << c.k;
        EXPECT_EQ(best[at], reference[at]) << c.rows << " x " << c.n << " k " << c.k;
      }
    }
    // Float sums of n terms: well inside n * 2^-24 of the sum of the terms' magnitudes.
    EXPECT_LT(worst, 1e-6 * scale) << c.rows << " x " << c.n << " k " << c.k;
  }
  std::printf("AVX2 path %s on this CPU\n", simd::Avx2() ? "taken" : "not available");
}

}  // namespace
}  // namespace irmosaic
