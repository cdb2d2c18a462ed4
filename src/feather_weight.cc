// Seam-blending weights of an undistorted frame (see feather_weight.h).
#include "feather_weight.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <opencv2/core/hal/intrin.hpp>

#include "simd_dispatch.h"

#if defined(__x86_64__)
#include <immintrin.h>
#endif

namespace irmosaic::feather {
namespace {

// Per edge: (distance + 0.5) / feather = ax * x + ay * y + c, inward positive (float, as every
// path evaluates it).
struct Edges {
  std::array<float, 4> ax, ay, c;
};

Edges EdgesOf(const std::array<Eigen::Vector2d, 4>& q, double feather_px) {
  double area2 = 0.0;
  for (int k = 0; k < 4; ++k) {
    const Eigen::Vector2d& a = q[k];
    const Eigen::Vector2d& b = q[(k + 1) % 4];
    area2 += a.x() * b.y() - b.x() * a.y();
  }
  const double orientation = area2 >= 0.0 ? 1.0 : -1.0;
  const double inv_feather = 1.0 / feather_px;
  Edges e;
  for (int k = 0; k < 4; ++k) {
    const Eigen::Vector2d d = q[(k + 1) % 4] - q[k];
    const double len = std::max(d.norm(), 1e-9);
    const Eigen::Vector2d inward = orientation * Eigen::Vector2d(-d.y(), d.x()) / len;
    e.ax[k] = static_cast<float>(inward.x() * inv_feather);
    e.ay[k] = static_cast<float>(inward.y() * inv_feather);
    e.c[k] = static_cast<float>((0.5 - inward.dot(q[k])) * inv_feather);
  }
  return e;
}

// One pixel: the reference's operations, in its order.
inline float PixelWeight(const Edges& e, const std::array<float, 4>& base, uint8_t inside, int x) {
  const float fx = static_cast<float>(x);
  float v = std::min(std::min(e.ax[0] * fx + base[0], e.ax[1] * fx + base[1]),
                     std::min(e.ax[2] * fx + base[2], e.ax[3] * fx + base[3]));
  v = std::min(std::max(v, 0.0f), 1.0f);
  return inside ? v : 0.0f;
}

// The columns [first, last) of a row outside which every edge function (base + ax * x) of
// some edge is at most zero, so the weight is 0 whatever the mask: the bounds are solved in
// double with a tolerance far above the float evaluation's rounding (~1e-7 of the terms) and
// widened by two pixels.
std::pair<int, int> PositiveSpan(const Edges& e, const std::array<float, 4>& base, int cols) {
  double first = 0.0, last = cols;
  for (int k = 0; k < 4; ++k) {
    const double a = e.ax[k], b = base[k];
    const double tol = 1e-4 * (1.0 + std::abs(a) * cols + std::abs(b));
    if (a > 0.0) {
      first = std::max(first, std::floor((-b - tol) / a) - 2.0);
    } else if (a < 0.0) {
      last = std::min(last, std::ceil((-b - tol) / a) + 2.0);
    } else if (b < -tol) {
      return {0, 0};
    }
  }
  if (!(first < last)) return {0, 0};
  return {static_cast<int>(std::max(0.0, first)), static_cast<int>(std::min<double>(cols, last))};
}

#if defined(__x86_64__)
__attribute__((target("avx2"))) void SpanAvx2(const Edges& e, const std::array<float, 4>& base,
                                              const uint8_t* inside, float* row, int x0, int x1) {
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  const __m256 ramp = _mm256_setr_ps(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f);
  const __m256 a0 = _mm256_set1_ps(e.ax[0]), a1 = _mm256_set1_ps(e.ax[1]);
  const __m256 a2 = _mm256_set1_ps(e.ax[2]), a3 = _mm256_set1_ps(e.ax[3]);
  const __m256 b0 = _mm256_set1_ps(base[0]), b1 = _mm256_set1_ps(base[1]);
  const __m256 b2 = _mm256_set1_ps(base[2]), b3 = _mm256_set1_ps(base[3]);
  int x = x0;
  for (; x + 8 <= x1; x += 8) {
    const __m256 fx = _mm256_add_ps(_mm256_set1_ps(static_cast<float>(x)), ramp);
    const __m256 v = _mm256_min_ps(_mm256_min_ps(_mm256_add_ps(_mm256_mul_ps(a0, fx), b0),
                                                 _mm256_add_ps(_mm256_mul_ps(a1, fx), b1)),
                                   _mm256_min_ps(_mm256_add_ps(_mm256_mul_ps(a2, fx), b2),
                                                 _mm256_add_ps(_mm256_mul_ps(a3, fx), b3)));
    const __m256i in =
        _mm256_cvtepu8_epi32(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(inside + x)));
    const __m256 outside = _mm256_castsi256_ps(_mm256_cmpeq_epi32(in, _mm256_setzero_si256()));
    _mm256_storeu_ps(row + x,
                     _mm256_andnot_ps(outside, _mm256_min_ps(_mm256_max_ps(v, zero), one)));
  }
  for (; x < x1; ++x) row[x] = PixelWeight(e, base, inside[x], x);
}
#endif

void SpanBaseline(const Edges& e, const std::array<float, 4>& base, const uint8_t* inside,
                  float* row, int x0, int x1) {
  int x = x0;
#if CV_SIMD128
  // Four pixels per vector, the scalar operations in their order (multiply, add, min, clamp).
  const cv::v_float32x4 zero = cv::v_setzero_f32(), one = cv::v_setall_f32(1.0f);
  const cv::v_float32x4 ramp(0.0f, 1.0f, 2.0f, 3.0f);
  std::array<cv::v_float32x4, 4> vax, vbase;
  for (int k = 0; k < 4; ++k) {
    vax[k] = cv::v_setall_f32(e.ax[k]);
    vbase[k] = cv::v_setall_f32(base[k]);
  }
  for (; x + 4 <= x1; x += 4) {
    const cv::v_float32x4 fx = cv::v_setall_f32(static_cast<float>(x)) + ramp;
    const cv::v_float32x4 v = cv::v_min(cv::v_min(vax[0] * fx + vbase[0], vax[1] * fx + vbase[1]),
                                        cv::v_min(vax[2] * fx + vbase[2], vax[3] * fx + vbase[3]));
    // Outside the mask: all bits cleared (0.0f). The 4 mask bytes are copied to a word first
    // (v_load_expand_q reads them as one 32-bit load).
    uint32_t word = 0;
    std::memcpy(&word, inside + x, sizeof(word));
    const cv::v_uint32x4 in = cv::v_load_expand_q(reinterpret_cast<const uchar*>(&word));
    const cv::v_float32x4 keep = cv::v_reinterpret_as_f32(in != cv::v_setzero_u32());
    cv::v_store(row + x, cv::v_min(cv::v_max(v, zero), one) & keep);
  }
#endif
  for (; x < x1; ++x) row[x] = PixelWeight(e, base, inside[x], x);
}

std::array<float, 4> RowBase(const Edges& e, int y) {
  std::array<float, 4> base;
  for (int k = 0; k < 4; ++k) base[k] = e.ay[k] * static_cast<float>(y) + e.c[k];
  return base;
}

}  // namespace

void Weight(const std::array<Eigen::Vector2d, 4>& quad, double feather_px, const cv::Mat& mask,
            cv::Mat* weight) {
  const Edges e = EdgesOf(quad, feather_px);
  weight->create(mask.size(), CV_32F);
  bool avx2 = false;
#if defined(__x86_64__)
  avx2 = simd::Avx2();
#endif
  for (int y = 0; y < weight->rows; ++y) {
    float* row = weight->ptr<float>(y);
    const uint8_t* inside = mask.ptr<uint8_t>(y);
    const std::array<float, 4> base = RowBase(e, y);
    const auto [x0, x1] = PositiveSpan(e, base, weight->cols);
    if (x0 >= x1) {
      std::fill(row, row + weight->cols, 0.0f);
      continue;
    }
    std::fill(row, row + x0, 0.0f);
    std::fill(row + x1, row + weight->cols, 0.0f);
#if defined(__x86_64__)
    if (avx2) {
      SpanAvx2(e, base, inside, row, x0, x1);
      continue;
    }
#endif
    SpanBaseline(e, base, inside, row, x0, x1);
  }
}

void WeightScalar(const std::array<Eigen::Vector2d, 4>& quad, double feather_px,
                  const cv::Mat& mask, cv::Mat* weight) {
  const Edges e = EdgesOf(quad, feather_px);
  weight->create(mask.size(), CV_32F);
  for (int y = 0; y < weight->rows; ++y) {
    float* row = weight->ptr<float>(y);
    const uint8_t* inside = mask.ptr<uint8_t>(y);
    const std::array<float, 4> base = RowBase(e, y);
    for (int x = 0; x < weight->cols; ++x) row[x] = PixelWeight(e, base, inside[x], x);
  }
}

}  // namespace irmosaic::feather
