#include "irmosaic/lsm.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "bank_projection.h"
#include "cubic_weights.h"
#include "irmosaic/error.h"

#if defined(__SSE2__)
#include <emmintrin.h>
#endif
#if defined(__GNUC__) && defined(__x86_64__)
// AVX2 paths built beside the baseline and chosen at run time (src/simd_dispatch.h).
#define IRMOSAIC_AVX2_PATHS 1
#include <immintrin.h>
#endif

#include "simd_dispatch.h"

namespace irmosaic {
namespace {

// The Freeman-Adelson table (their Fig. 13 / Table 1), g = exp(-(x^2 + y^2)).
double BasisValue(int k, double x, double y) {
  const double g = std::exp(-(x * x + y * y));
  switch (k) {
    case 0:
      return 0.9213 * (2.0 * x * x - 1.0) * g;
    case 1:
      return 1.843 * x * y * g;
    case 2:
      return 0.9213 * (2.0 * y * y - 1.0) * g;
    case 3:
      return 0.9780 * (-2.254 * x + x * x * x) * g;
    case 4:
      return 0.9780 * (-0.7515 + x * x) * y * g;
    case 5:
      return 0.9780 * (-0.7515 + y * y) * x * g;
    default:
      return 0.9780 * (-2.254 * y + y * y * y) * g;
  }
}

std::string Describe(const char* what, double value, const char* limit, double bound) {
  std::ostringstream s;
  s << what << " " << value << " " << limit << " " << bound;
  return s.str();
}

// Displacement of the farthest patch corner under x -> x + d + D x.
double CornerMotion(const Eigen::Vector2d& d, const Eigen::Matrix2d& lin, int r) {
  double worst = 0.0;
  for (int sy = -1; sy <= 1; sy += 2) {
    for (int sx = -1; sx <= 1; sx += 2) {
      worst = std::max(worst, (d + lin * Eigen::Vector2d(sx * r, sy * r)).norm());
    }
  }
  return worst;
}

// Condition number of a matrix after scaling its columns to unit norm (0 when a column is
// null: no texture at all), from the eigenvalues of the scaled columns' Gram matrix (the
// squared singular values): a few columns' small symmetric eigenproblem instead of an SVD of
// all the rows. Squaring costs digits only near a condition of 1e8, far above any bound used.
double NormalisedCondition(const Eigen::MatrixXd& a) {
  const Eigen::VectorXd norms = a.colwise().norm().transpose();
  for (int j = 0; j < norms.size(); ++j) {
    if (!(norms(j) > 1e-12)) return 0.0;
  }
  const Eigen::VectorXd inv = norms.cwiseInverse();
  const Eigen::MatrixXd gram = inv.asDiagonal() * (a.transpose() * a) * inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(gram, Eigen::EigenvaluesOnly);
  const Eigen::VectorXd& e = eig.eigenvalues();  // Ascending.
  if (!(e(0) > 0.0)) return std::numeric_limits<double>::infinity();
  return std::sqrt(e(e.size() - 1) / e(0));
}

// Extracts the (2r+3)^2 template patch around p (bilinear for a non-integer p); false when it
// does not fit in the image.
bool TemplatePatch(const cv::Mat& templ, const Eigen::Vector2d& p, int r, cv::Mat* out) {
  const int half = r + 1;
  if (p.x() - half < 0 || p.y() - half < 0 || p.x() + half > templ.cols - 1 ||
      p.y() + half > templ.rows - 1) {
    return false;
  }
  const int size = 2 * half + 1;
  if (p.x() == std::floor(p.x()) && p.y() == std::floor(p.y())) {
    templ(cv::Rect(static_cast<int>(p.x()) - half, static_cast<int>(p.y()) - half, size, size))
        .copyTo(*out);
  } else {
    cv::getRectSubPix(templ, cv::Size(size, size), cv::Point2f(p.x(), p.y()), *out, CV_32F);
  }
  return true;
}

#if defined(__SSE2__)
// The same weights for 4 offsets at once, operation for operation as CubicWeights (no fused
// multiply-add, same association), so each lane is bit-identical to the scalar weights.
inline void CubicWeights4(__m128 t, __m128* w) {
  const __m128 t2 = _mm_mul_ps(t, t), t3 = _mm_mul_ps(t2, t);
  const __m128 half = _mm_set1_ps(0.5f), minus_half = _mm_set1_ps(-0.5f);
  w[0] = _mm_sub_ps(_mm_add_ps(_mm_mul_ps(minus_half, t3), t2), _mm_mul_ps(half, t));
  w[1] =
      _mm_add_ps(_mm_sub_ps(_mm_mul_ps(_mm_set1_ps(1.5f), t3), _mm_mul_ps(_mm_set1_ps(2.5f), t2)),
                 _mm_set1_ps(1.0f));
  w[2] =
      _mm_add_ps(_mm_add_ps(_mm_mul_ps(_mm_set1_ps(-1.5f), t3), _mm_mul_ps(_mm_set1_ps(2.0f), t2)),
                 _mm_mul_ps(half, t));
  w[3] = _mm_sub_ps(_mm_mul_ps(half, t3), _mm_mul_ps(half, t2));
}

// Integer parts (truncation, as static_cast<int>) and fractional parts (as float) of the 4
// positions start + step * (u + k), k = 0..3, computed in double as the scalar sampler does.
inline void SplitPositions4(double start, double step, int u, int* whole, __m128* fraction) {
  const __m128d steps = _mm_set1_pd(step), origin = _mm_set1_pd(start);
  const __m128d lo = _mm_add_pd(origin, _mm_mul_pd(steps, _mm_set_pd(u + 1, u)));
  const __m128d hi = _mm_add_pd(origin, _mm_mul_pd(steps, _mm_set_pd(u + 3, u + 2)));
  const __m128i whole_lo = _mm_cvttpd_epi32(lo), whole_hi = _mm_cvttpd_epi32(hi);
  const __m128 frac_lo = _mm_cvtpd_ps(_mm_sub_pd(lo, _mm_cvtepi32_pd(whole_lo)));
  const __m128 frac_hi = _mm_cvtpd_ps(_mm_sub_pd(hi, _mm_cvtepi32_pd(whole_hi)));
  *fraction = _mm_movelh_ps(frac_lo, frac_hi);
  _mm_storeu_si128(reinterpret_cast<__m128i*>(whole), _mm_unpacklo_epi64(whole_lo, whole_hi));
}
#endif

#if IRMOSAIC_AVX2_PATHS
// CubicWeights4 for 8 offsets: the same operations in the same order (AVX2 without FMA), so
// each lane is bit-identical to the scalar and SSE2 weights.
__attribute__((target("avx2"))) inline void CubicWeights8(__m256 t, __m256* w) {
  const __m256 t2 = _mm256_mul_ps(t, t), t3 = _mm256_mul_ps(t2, t);
  const __m256 half = _mm256_set1_ps(0.5f), minus_half = _mm256_set1_ps(-0.5f);
  w[0] = _mm256_sub_ps(_mm256_add_ps(_mm256_mul_ps(minus_half, t3), t2), _mm256_mul_ps(half, t));
  w[1] = _mm256_add_ps(_mm256_sub_ps(_mm256_mul_ps(_mm256_set1_ps(1.5f), t3),
                                     _mm256_mul_ps(_mm256_set1_ps(2.5f), t2)),
                       _mm256_set1_ps(1.0f));
  w[2] = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(_mm256_set1_ps(-1.5f), t3),
                                     _mm256_mul_ps(_mm256_set1_ps(2.0f), t2)),
                       _mm256_mul_ps(half, t));
  w[3] = _mm256_sub_ps(_mm256_mul_ps(half, t3), _mm256_mul_ps(half, t2));
}

// SplitPositions4 for the 8 positions start + step * (u + k), k = 0..7.
__attribute__((target("avx2"))) inline void SplitPositions8(double start, double step, int u,
                                                            int* whole, __m256* fraction) {
  const __m256d steps = _mm256_set1_pd(step), origin = _mm256_set1_pd(start);
  const __m256d lo =
      _mm256_add_pd(origin, _mm256_mul_pd(steps, _mm256_set_pd(u + 3, u + 2, u + 1, u)));
  const __m256d hi =
      _mm256_add_pd(origin, _mm256_mul_pd(steps, _mm256_set_pd(u + 7, u + 6, u + 5, u + 4)));
  const __m128i whole_lo = _mm256_cvttpd_epi32(lo), whole_hi = _mm256_cvttpd_epi32(hi);
  const __m128 frac_lo = _mm256_cvtpd_ps(_mm256_sub_pd(lo, _mm256_cvtepi32_pd(whole_lo)));
  const __m128 frac_hi = _mm256_cvtpd_ps(_mm256_sub_pd(hi, _mm256_cvtepi32_pd(whole_hi)));
  *fraction = _mm256_insertf128_ps(_mm256_castps128_ps256(frac_lo), frac_hi, 1);
  _mm_storeu_si128(reinterpret_cast<__m128i*>(whole), whole_lo);
  _mm_storeu_si128(reinterpret_cast<__m128i*>(whole + 4), whole_hi);
}

// out[u] = ((w0 a0[u] + w1 a1[u]) + w2 a2[u]) + w3 a3[u] for u < n, as the separable warp's
// SSE2 and scalar loops compute it; returns how many were done (n, or 0 when n < 8).
__attribute__((target("avx2"))) int Weighted4Avx2(const float* a0, const float* a1, const float* a2,
                                                  const float* a3, const float* w, int n,
                                                  float* out) {
  const __m256 w0 = _mm256_set1_ps(w[0]), w1 = _mm256_set1_ps(w[1]), w2 = _mm256_set1_ps(w[2]),
               w3 = _mm256_set1_ps(w[3]);
  if (n < 8) return 0;
  for (int start = 0; start < n; start += 8) {
    // The last group ends at n, overlapping the one before: its pixels come out the same.
    const int u = std::min(start, n - 8);
    const __m256 sum =
        _mm256_add_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(w0, _mm256_loadu_ps(a0 + u)),
                                                  _mm256_mul_ps(w1, _mm256_loadu_ps(a1 + u))),
                                    _mm256_mul_ps(w2, _mm256_loadu_ps(a2 + u))),
                      _mm256_mul_ps(w3, _mm256_loadu_ps(a3 + u)));
    _mm256_storeu_ps(out + u, sum);
  }
  return n;
}

// Four floats from lo in the low half, four from hi in the high half.
__attribute__((target("avx2"))) inline __m256 Load2(const float* lo, const float* hi) {
  return _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(lo)), _mm_loadu_ps(hi), 1);
}

// One row of the affine bicubic warp, 8 pixels at a time: the SSE2 loop of WarpPatch with
// lanes k and k + 4 in the two halves of each register (the 4 x 4 transposes stay within
// halves); returns how many pixels were done (size, or 0 when size < 8).
__attribute__((target("avx2"))) int WarpAffineRowAvx2(const cv::Mat& base, double row_x,
                                                      double row_y, double m00, double m10,
                                                      int size, float* dst) {
  const size_t step = base.step1();
  if (size < 8) return 0;
  for (int start = 0; start < size; start += 8) {
    // The last group ends at size, overlapping the one before: its pixels come out the same.
    const int u = std::min(start, size - 8);
    int x0[8], y0[8];
    __m256 tx, ty, wx[4], wy[4];
    SplitPositions8(row_x, m00, u, x0, &tx);
    SplitPositions8(row_y, m10, u, y0, &ty);
    CubicWeights8(tx, wx);
    CubicWeights8(ty, wy);
    const float* p[8];
    for (int k = 0; k < 8; ++k) p[k] = base.ptr<float>(y0[k] - 1) + x0[k] - 1;
    __m256 sum = _mm256_setzero_ps();
    for (int j = 0; j < 4; ++j) {
      const size_t o = j * step;
      const __m256 r0 = Load2(p[0] + o, p[4] + o), r1 = Load2(p[1] + o, p[5] + o);
      const __m256 r2 = Load2(p[2] + o, p[6] + o), r3 = Load2(p[3] + o, p[7] + o);
      const __m256 t0 = _mm256_unpacklo_ps(r0, r1), t1 = _mm256_unpacklo_ps(r2, r3);
      const __m256 t2 = _mm256_unpackhi_ps(r0, r1), t3 = _mm256_unpackhi_ps(r2, r3);
      const __m256 tap0 = _mm256_shuffle_ps(t0, t1, _MM_SHUFFLE(1, 0, 1, 0));
      const __m256 tap1 = _mm256_shuffle_ps(t0, t1, _MM_SHUFFLE(3, 2, 3, 2));
      const __m256 tap2 = _mm256_shuffle_ps(t2, t3, _MM_SHUFFLE(1, 0, 1, 0));
      const __m256 tap3 = _mm256_shuffle_ps(t2, t3, _MM_SHUFFLE(3, 2, 3, 2));
      const __m256 across = _mm256_add_ps(
          _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(wx[0], tap0), _mm256_mul_ps(wx[1], tap1)),
                        _mm256_mul_ps(wx[2], tap2)),
          _mm256_mul_ps(wx[3], tap3));
      sum = _mm256_add_ps(sum, _mm256_mul_ps(wy[j], across));
    }
    _mm256_storeu_ps(dst + u, sum);
  }
  return size;
}
#endif

}  // namespace

const char* ToString(LsmResult::Status status) {
  switch (status) {
    case LsmResult::Status::kConverged:
      return "converged";
    case LsmResult::Status::kNotConverged:
      return "not_converged";
    case LsmResult::Status::kDiverged:
      return "diverged";
    case LsmResult::Status::kLowTexture:
      return "low_texture";
    case LsmResult::Status::kIllConditioned:
      return "ill_conditioned";
    case LsmResult::Status::kOutOfBounds:
      return "out_of_bounds";
    case LsmResult::Status::kBadInput:
      return "bad_input";
  }
  return "unknown";
}

bool LsmOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (method == LsmMethod::kFast && scales_px.empty()) return fail("scales_px is empty");
  for (double s : scales_px) {
    if (!(s >= 1.0 && s <= 100.0)) return fail("each of scales_px must be in [1, 100] px");
  }
  if (!(support_in_scales >= 1.5 && support_in_scales <= 5.0)) {
    return fail("support_in_scales must be in [1.5, 5]");
  }
  if (tlsm_radius_px < 0 || tlsm_radius_px > 200) return fail("tlsm_radius_px must be in [0, 200]");
  if (translation_only_iterations < 0) return fail("translation_only_iterations must be >= 0");
  if (max_iterations < 1 || max_iterations > 1000)
    return fail("max_iterations must be in [1, 1000]");
  if (!(convergence_px > 0.0)) return fail("convergence_px must be > 0");
  if (!(max_shift_px > 0.0)) return fail("max_shift_px must be > 0");
  if (!(max_affine_deviation > 0.0 && max_affine_deviation < 1.0)) {
    return fail("max_affine_deviation must be in (0, 1)");
  }
  if (!(max_condition > 1.0)) return fail("max_condition must be > 1");
  if (!(max_position_sigma_px > 0.0)) return fail("max_position_sigma_px must be > 0");
  return true;
}

std::vector<cv::Mat> SteerableBasisFilters(double scale_px, int radius_px, bool zero_mean) {
  const int size = 2 * radius_px + 1;
  cv::Mat envelope(size, size, CV_64F);
  std::vector<cv::Mat> filters(7);
  for (int k = 0; k < 7; ++k) filters[k].create(size, size, CV_64F);
  for (int v = -radius_px; v <= radius_px; ++v) {
    for (int u = -radius_px; u <= radius_px; ++u) {
      const double x = u / scale_px, y = v / scale_px;
      envelope.at<double>(v + radius_px, u + radius_px) = std::exp(-(x * x + y * y));
      for (int k = 0; k < 7; ++k) {
        filters[k].at<double>(v + radius_px, u + radius_px) = BasisValue(k, x, y);
      }
    }
  }
  if (zero_mean) {
    // Removing a multiple of the envelope (not a constant) keeps the filter local.
    const double envelope_sum = cv::sum(envelope)[0];
    for (cv::Mat& f : filters) {
      f -= envelope * (cv::sum(f)[0] / envelope_sum);
      f /= cv::norm(f, cv::NORM_L2);
    }
  }
  return filters;
}

LsmMatcher::LsmMatcher(LsmOptions options) : options_(std::move(options)) {
  std::string error;
  if (!options_.IsValid(&error)) {
    throw InputError(SourceLocation{"LsmOptions", 0, 0, ""}, error, "fix the option");
  }
  double largest = 0.0;
  for (double s : options_.scales_px) largest = std::max(largest, s);
  const int flsm_radius = static_cast<int>(std::ceil(options_.support_in_scales * largest));
  if (options_.method == LsmMethod::kTraditional) {
    radius_ = options_.tlsm_radius_px > 0 ? options_.tlsm_radius_px : flsm_radius;
    return;
  }
  radius_ = flsm_radius;
  const int size = 2 * radius_ + 1;
  bank_.resize(7 * static_cast<int>(options_.scales_px.size()), size * size);
  int row = 0;
  for (double s : options_.scales_px) {
    for (const cv::Mat& f : SteerableBasisFilters(s, radius_, true)) {
      for (int i = 0; i < size * size; ++i) bank_(row, i) = static_cast<float>(f.at<double>(i));
      ++row;
    }
  }
  {
    // Orthonormalise the bank's rows (same span): the 21 equations then carry independent,
    // equal noise, so least squares on them is the best linear estimate for white noise.
    const Eigen::MatrixXd b = bank_.cast<double>();
    const Eigen::MatrixXd gram = b * b.transpose();
    const Eigen::LLT<Eigen::MatrixXd> llt(gram);
    bank_ = llt.matrixL().solve(b).cast<float>();
  }
}

bool LsmMatcher::WarpPatch(const cv::Mat& base, const Eigen::Vector2d& c, const Eigen::Matrix2d& m,
                           int r, cv::Mat* out) {
  // Bounds: an affine image of the square is inside the image iff its 4 corners are; the
  // cubic kernel reads one more pixel on each side.
  for (int sy = -1; sy <= 1; sy += 2) {
    for (int sx = -1; sx <= 1; sx += 2) {
      const Eigen::Vector2d q = c + m * Eigen::Vector2d(sx * r, sy * r);
      if (!(q.x() >= 1.0 && q.y() >= 1.0 && q.x() < base.cols - 3 && q.y() < base.rows - 3)) {
        return false;
      }
    }
  }
  const int size = 2 * r + 1;
  out->create(size, size, CV_32F);
#if IRMOSAIC_AVX2_PATHS
  const bool avx2 = simd::Avx2();
#endif
  // Own bicubic sampler (Keys, a = -0.5): cv::warpAffine quantises positions to 1/32 px, and
  // bilinear interpolation biases sub-pixel positions by a few hundredths of a pixel.
  // With SSE2, 4 output pixels go through the vector lanes at once; every lane performs the
  // scalar sampler's operations in its order, so the patch is bit-identical either way.
  if (m == Eigen::Matrix2d::Identity()) {
    // Pure translation (the first iterations): one fractional offset for the whole patch, so
    // the bicubic kernel is separable: a horizontal pass, then a vertical one.
    const int x0 = static_cast<int>(c.x()) - r, y0 = static_cast<int>(c.y()) - r;
    float wx[4], wy[4];
    CubicWeights(static_cast<float>(c.x() - static_cast<int>(c.x())), wx);
    CubicWeights(static_cast<float>(c.y() - static_cast<int>(c.y())), wy);
    rows_.create(size + 3, size, CV_32F);
    for (int j = 0; j < size + 3; ++j) {
      const float* p = base.ptr<float>(y0 - 1 + j) + x0 - 1;
      float* h = rows_.ptr<float>(j);
      int u = 0;
#if IRMOSAIC_AVX2_PATHS
      if (avx2) u = Weighted4Avx2(p, p + 1, p + 2, p + 3, wx, size, h);
#endif
#if defined(__SSE2__)
      const __m128 w0 = _mm_set1_ps(wx[0]), w1 = _mm_set1_ps(wx[1]), w2 = _mm_set1_ps(wx[2]),
                   w3 = _mm_set1_ps(wx[3]);
      // The last group ends at size, overlapping the one before (its pixels come out the same).
      for (int next = u; size >= 4 && next < size; next += 4) {
        u = std::min(next, size - 4);
        const __m128 sum =
            _mm_add_ps(_mm_add_ps(_mm_add_ps(_mm_mul_ps(w0, _mm_loadu_ps(p + u)),
                                             _mm_mul_ps(w1, _mm_loadu_ps(p + u + 1))),
                                  _mm_mul_ps(w2, _mm_loadu_ps(p + u + 2))),
                       _mm_mul_ps(w3, _mm_loadu_ps(p + u + 3)));
        _mm_storeu_ps(h + u, sum);
      }
      if (size >= 4) u = size;
#endif
      for (; u < size; ++u) {
        h[u] = wx[0] * p[u] + wx[1] * p[u + 1] + wx[2] * p[u + 2] + wx[3] * p[u + 3];
      }
    }
    for (int v = 0; v < size; ++v) {
      const float* h0 = rows_.ptr<float>(v);
      const float* h1 = rows_.ptr<float>(v + 1);
      const float* h2 = rows_.ptr<float>(v + 2);
      const float* h3 = rows_.ptr<float>(v + 3);
      float* dst = out->ptr<float>(v);
      int u = 0;
#if IRMOSAIC_AVX2_PATHS
      if (avx2) u = Weighted4Avx2(h0, h1, h2, h3, wy, size, dst);
#endif
#if defined(__SSE2__)
      const __m128 w0 = _mm_set1_ps(wy[0]), w1 = _mm_set1_ps(wy[1]), w2 = _mm_set1_ps(wy[2]),
                   w3 = _mm_set1_ps(wy[3]);
      // The last group ends at size, overlapping the one before (its pixels come out the same).
      for (int next = u; size >= 4 && next < size; next += 4) {
        u = std::min(next, size - 4);
        const __m128 sum = _mm_add_ps(_mm_add_ps(_mm_add_ps(_mm_mul_ps(w0, _mm_loadu_ps(h0 + u)),
                                                            _mm_mul_ps(w1, _mm_loadu_ps(h1 + u))),
                                                 _mm_mul_ps(w2, _mm_loadu_ps(h2 + u))),
                                      _mm_mul_ps(w3, _mm_loadu_ps(h3 + u)));
        _mm_storeu_ps(dst + u, sum);
      }
      if (size >= 4) u = size;
#endif
      for (; u < size; ++u) {
        dst[u] = wy[0] * h0[u] + wy[1] * h1[u] + wy[2] * h2[u] + wy[3] * h3[u];
      }
    }
    return true;
  }
  const size_t step = base.step1();
  for (int v = 0; v < size; ++v) {
    float* dst = out->ptr<float>(v);
    const double row_x = c.x() + m(0, 0) * (-r) + m(0, 1) * (v - r);
    const double row_y = c.y() + m(1, 0) * (-r) + m(1, 1) * (v - r);
    int u = 0;
#if IRMOSAIC_AVX2_PATHS
    if (avx2) u = WarpAffineRowAvx2(base, row_x, row_y, m(0, 0), m(1, 0), size, dst);
#endif
#if defined(__SSE2__)
    // The last group ends at size, overlapping the one before (its pixels come out the same).
    for (int next = u; size >= 4 && next < size; next += 4) {
      u = std::min(next, size - 4);
      int x0[4], y0[4];
      __m128 tx, ty, wx[4], wy[4];
      SplitPositions4(row_x, m(0, 0), u, x0, &tx);
      SplitPositions4(row_y, m(1, 0), u, y0, &ty);
      CubicWeights4(tx, wx);
      CubicWeights4(ty, wy);
      const float* p[4];
      for (int k = 0; k < 4; ++k) p[k] = base.ptr<float>(y0[k] - 1) + x0[k] - 1;
      __m128 sum = _mm_setzero_ps();
      for (int j = 0; j < 4; ++j) {
        // Row j of the 4 x 4 neighbourhood of each lane's pixel, transposed so that tap i of
        // all 4 lanes sits in one register.
        __m128 tap0 = _mm_loadu_ps(p[0] + j * step), tap1 = _mm_loadu_ps(p[1] + j * step);
        __m128 tap2 = _mm_loadu_ps(p[2] + j * step), tap3 = _mm_loadu_ps(p[3] + j * step);
        _MM_TRANSPOSE4_PS(tap0, tap1, tap2, tap3);
        const __m128 across =
            _mm_add_ps(_mm_add_ps(_mm_add_ps(_mm_mul_ps(wx[0], tap0), _mm_mul_ps(wx[1], tap1)),
                                  _mm_mul_ps(wx[2], tap2)),
                       _mm_mul_ps(wx[3], tap3));
        sum = _mm_add_ps(sum, _mm_mul_ps(wy[j], across));
      }
      _mm_storeu_ps(dst + u, sum);
    }
    if (size >= 4) u = size;
#endif
    for (; u < size; ++u) {
      const double x = row_x + m(0, 0) * u, y = row_y + m(1, 0) * u;
      const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
      float wx[4], wy[4];
      CubicWeights(static_cast<float>(x - x0), wx);
      CubicWeights(static_cast<float>(y - y0), wy);
      float sum = 0.0f;
      const float* p = base.ptr<float>(y0 - 1) + x0 - 1;
      for (int j = 0; j < 4; ++j, p += step) {
        sum += wy[j] * (wx[0] * p[0] + wx[1] * p[1] + wx[2] * p[2] + wx[3] * p[3]);
      }
      dst[u] = sum;
    }
  }
  return true;
}

LsmResult LsmMatcher::MatchProjected(const cv::Mat& base, const Eigen::MatrixXd& projected,
                                     const Eigen::Vector2d& initial_in_base,
                                     const Eigen::Matrix2d& initial_linear) {
  LsmResult result;
  result.position_in_base = initial_in_base;
  result.base_from_template_linear = initial_linear;
  if (base.empty() || base.type() != CV_32FC1 || options_.method != LsmMethod::kFast ||
      projected.rows() != bank_.rows() || projected.cols() != 7) {
    result.reason = "needs a non-empty CV_32FC1 base, the FLSM method and 21 x 7 projections";
    return result;
  }
  if (!initial_in_base.allFinite() || !initial_linear.allFinite() ||
      std::abs(initial_linear.determinant()) < 1e-6) {
    result.reason = "initial position or initial affine is not finite or singular";
    return result;
  }
  return MatchFastProjected(base, projected, initial_in_base, initial_linear);
}

LsmResult LsmMatcher::Match(const cv::Mat& base, const cv::Mat& templ,
                            const Eigen::Vector2d& point_in_template,
                            const Eigen::Vector2d& initial_in_base,
                            const Eigen::Matrix2d& initial_linear) {
  LsmResult result;
  result.position_in_base = initial_in_base;
  result.base_from_template_linear = initial_linear;
  if (base.empty() || templ.empty() || base.type() != CV_32FC1 || templ.type() != CV_32FC1) {
    result.reason = "base and template must be non-empty CV_32FC1 images";
    return result;
  }
  if (!point_in_template.allFinite() || !initial_in_base.allFinite() ||
      !initial_linear.allFinite() || std::abs(initial_linear.determinant()) < 1e-6) {
    result.reason = "point, initial position or initial affine is not finite or singular";
    return result;
  }
  return options_.method == LsmMethod::kFast
             ? MatchFast(base, templ, point_in_template, initial_in_base, initial_linear)
             : MatchTraditional(base, templ, point_in_template, initial_in_base, initial_linear);
}

namespace {

// Shared end-of-iteration checks; returns true when the loop must stop with `result` set.
bool CheckDivergence(const LsmOptions& o, const Eigen::Vector2d& c0, const Eigen::Vector2d& c,
                     const Eigen::Matrix2d& m0, const Eigen::Matrix2d& m, double gain,
                     LsmResult* result) {
  if (!c.allFinite() || !m.allFinite() || !std::isfinite(gain)) {
    result->status = LsmResult::Status::kDiverged;
    result->reason = "the estimate became non-finite";
    return true;
  }
  if ((c - c0).norm() > o.max_shift_px) {
    result->status = LsmResult::Status::kDiverged;
    result->reason =
        Describe("moved", (c - c0).norm(), "px from its start, more than", o.max_shift_px);
    return true;
  }
  const double deviation = (m0.inverse() * m - Eigen::Matrix2d::Identity()).cwiseAbs().maxCoeff();
  if (deviation > o.max_affine_deviation) {
    result->status = LsmResult::Status::kDiverged;
    result->reason = Describe("affine deviates by", deviation, "from its start, more than",
                              o.max_affine_deviation);
    return true;
  }
  if (!(gain > 0.1 && gain < 10.0)) {
    result->status = LsmResult::Status::kDiverged;
    result->reason = Describe("gain", gain, "outside", 0.1) + " .. 10";
    return true;
  }
  return false;
}

// A-posteriori std (px, larger axis) of the patch position from the normal matrix and the
// residual; `translation_rows` index the d_x, d_y unknowns in patch coordinates.
double PositionSigma(const Eigen::MatrixXd& normal, double residual_sq, int redundancy,
                     const Eigen::Matrix2d& m) {
  if (redundancy <= 0) return std::numeric_limits<double>::infinity();
  const Eigen::MatrixXd cov = normal.inverse() * (residual_sq / redundancy);
  Eigen::Matrix2d t;
  t << cov(0, 0), cov(0, 3), cov(3, 0), cov(3, 3);
  const Eigen::Matrix2d in_base = m * t * m.transpose();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(in_base);
  return std::sqrt(std::max(0.0, eig.eigenvalues()(1)));
}

// Solves the normal equations of a least-squares step; without `full`, only the two
// translations and the radiometric unknowns (columns 6..) are free and the affine part stays zero.
Eigen::VectorXd SolveNormal(const Eigen::MatrixXd& normal, const Eigen::VectorXd& rhs, bool full) {
  if (full) return normal.ldlt().solve(rhs);
  std::vector<int> cols = {0, 3};
  for (int j = 6; j < normal.cols(); ++j) cols.push_back(j);
  const int k = static_cast<int>(cols.size());
  Eigen::MatrixXd sub(k, k);
  Eigen::VectorXd sub_rhs(k);
  for (int i = 0; i < k; ++i) {
    sub_rhs(i) = rhs(cols[i]);
    for (int j = 0; j < k; ++j) sub(i, j) = normal(cols[i], cols[j]);
  }
  const Eigen::VectorXd x = sub.ldlt().solve(sub_rhs);
  Eigen::VectorXd delta = Eigen::VectorXd::Zero(normal.cols());
  for (int i = 0; i < k; ++i) delta(cols[i]) = x(i);
  return delta;
}

// One iteration's convergence bookkeeping, shared by both solvers: translation first, then
// (with estimate_affine) the full affine; converged when the update moves the patch corners
// less than convergence_px in the full stage. Updates *full; returns true when converged.
bool Settle(const LsmOptions& o, double corner_motion_px, int iteration, bool* full) {
  if (corner_motion_px < o.convergence_px) {
    if (*full || !o.estimate_affine) return true;
    *full = true;  // Translation settled: release the affine.
  }
  if (iteration >= o.translation_only_iterations && o.estimate_affine) *full = true;
  return false;
}

}  // namespace

bool LsmMatcher::ProjectTemplate(const cv::Mat& templ, const Eigen::Vector2d& p,
                                 Eigen::MatrixXd* projected) {
  const int r = radius_, size = 2 * r + 1, n = size * size;
  cv::Mat t;
  if (bank_.rows() == 0 || !TemplatePatch(templ, p, r, &t)) return false;
  // Design images of the inverse-compositional LSM, from the template patch: constant over
  // the iterations, so their 21 projections are computed once per key point. One image after
  // the other (image k at k n), for the projection.
  thread_local std::vector<float> design_images;  // Grown once, kept for the thread's pairs.
  design_images.resize(static_cast<size_t>(7) * n);
  float* design = design_images.data();
  const double inv_r = 1.0 / r;
  for (int v = 0; v < size; ++v) {
    const float* up = t.ptr<float>(v) + 1;
    const float* mid = t.ptr<float>(v + 1) + 1;
    const float* down = t.ptr<float>(v + 2) + 1;
    const float yn = static_cast<float>((v - r) * inv_r);
    for (int u = 0; u < size; ++u) {
      const float xn = static_cast<float>((u - r) * inv_r);
      const float ix = 0.5f * (mid[u + 1] - mid[u - 1]);
      const float iy = 0.5f * (down[u] - up[u]);
      const int i = v * size + u;
      design[i] = ix;
      design[n + i] = xn * ix;
      design[2 * n + i] = yn * ix;
      design[3 * n + i] = iy;
      design[4 * n + i] = xn * iy;
      design[5 * n + i] = yn * iy;
      design[6 * n + i] = mid[u];
    }
  }
  projected->resize(bank_.rows(), 7);  // 21 x 7, column-major.
  bank::Project(bank_.data(), static_cast<int>(bank_.rows()), n, design, 7, projected->data(),
                static_cast<int>(bank_.rows()));
  return true;
}

bool LsmMatcher::ProjectBase(const cv::Mat& base, const Eigen::Vector2d& c,
                             const Eigen::Matrix2d& m, Eigen::VectorXd* responses) {
  if (bank_.rows() == 0 || !WarpPatch(base, c, m, radius_, &warped_)) return false;
  responses->resize(bank_.rows());
  bank::Project(bank_.data(), static_cast<int>(bank_.rows()), static_cast<int>(warped_.total()),
                warped_.ptr<float>(), 1, responses->data(), 1);
  return true;
}

LsmResult LsmMatcher::MatchFast(const cv::Mat& base, const cv::Mat& templ, const Eigen::Vector2d& p,
                                const Eigen::Vector2d& c0, const Eigen::Matrix2d& m0) {
  Eigen::MatrixXd projected;
  if (!ProjectTemplate(templ, p, &projected)) {
    LsmResult result;
    result.position_in_base = c0;
    result.base_from_template_linear = m0;
    result.status = LsmResult::Status::kOutOfBounds;
    result.reason = "template patch does not fit in the template image";
    return result;
  }
  return MatchFastProjected(base, projected, c0, m0);
}

LsmResult LsmMatcher::MatchFastProjected(const cv::Mat& base, const Eigen::MatrixXd& projected,
                                         const Eigen::Vector2d& c0, const Eigen::Matrix2d& m0) {
  LsmResult result;
  result.position_in_base = c0;
  result.base_from_template_linear = m0;
  const int r = radius_, n = (2 * r + 1) * (2 * r + 1);
  const double inv_r = 1.0 / r;
  const int unknowns = options_.estimate_gain ? 7 : 6;
  result.condition = NormalisedCondition(projected.leftCols(unknowns));
  if (result.condition == 0.0) {
    result.status = LsmResult::Status::kLowTexture;
    result.reason = "flat patch: a filter projection of the gradients is zero";
    return result;
  }
  if (result.condition > options_.max_condition) {
    result.status = LsmResult::Status::kIllConditioned;
    result.reason = Describe("condition number", result.condition, "above", options_.max_condition);
    return result;
  }

  Eigen::Vector2d c = c0;
  Eigen::Matrix2d m = m0;
  double gain = 1.0;
  Eigen::VectorXd residual;
  Eigen::MatrixXd a(projected.rows(), unknowns);
  result.status = LsmResult::Status::kNotConverged;
  bool full = options_.translation_only_iterations == 0 && options_.estimate_affine;
  for (int it = 1; it <= options_.max_iterations; ++it) {
    result.iterations = it;
    if (!WarpPatch(base, c, m, r, &warped_)) {
      result.status = LsmResult::Status::kOutOfBounds;
      result.reason = "the warped patch left the base image";
      return result;
    }
    Eigen::VectorXd b(bank_.rows());
    bank::Project(bank_.data(), static_cast<int>(bank_.rows()), n, warped_.ptr<float>(), 1,
                  b.data(), 1);
    b -= gain * projected.col(6);
    a.leftCols(6) = gain * projected.leftCols(6);
    if (unknowns == 7) a.col(6) = projected.col(6);
    // Translation (and gain) first: under heavy noise a first full affine step from a
    // pixel away can jump far; the affine is released once the translation has settled.
    // Normal equations: the system (21 x 7 at most, condition <= max_condition) is far from
    // needing an orthogonal factorisation, which cost more than the rest of the step.
    const Eigen::VectorXd delta = SolveNormal(a.transpose() * a, a.transpose() * b, full);
    residual = b - a * delta;
    // Inverse composition: w(x) <- w(x) o (x + d + D x)^-1.
    const Eigen::Vector2d d(delta(0), delta(3));
    Eigen::Matrix2d lin;
    lin << delta(1) * inv_r, delta(2) * inv_r, delta(4) * inv_r, delta(5) * inv_r;
    m = m * (Eigen::Matrix2d::Identity() + lin).inverse();
    c = c - m * d;
    if (unknowns == 7) gain += delta(6);
    if (CheckDivergence(options_, c0, c, m0, m, gain, &result)) return result;
    if (Settle(options_, CornerMotion(d, lin, r), it, &full)) {
      result.status = LsmResult::Status::kConverged;
      break;
    }
  }
  result.position_in_base = c;
  result.base_from_template_linear = m;
  result.gain = gain;
  result.residual_rms = std::sqrt(residual.squaredNorm() / residual.size());
  result.position_sigma_px =
      PositionSigma(a.transpose() * a, residual.squaredNorm(), a.rows() - a.cols(), m);
  if (result.status == LsmResult::Status::kNotConverged) {
    result.reason = "still moving after max_iterations";
  } else if (!(result.position_sigma_px <= options_.max_position_sigma_px)) {
    result.status = LsmResult::Status::kLowTexture;
    result.reason = Describe("position sigma", result.position_sigma_px, "px above",
                             options_.max_position_sigma_px);
  }
  return result;
}

LsmResult LsmMatcher::MatchTraditional(const cv::Mat& base, const cv::Mat& templ,
                                       const Eigen::Vector2d& p, const Eigen::Vector2d& c0,
                                       const Eigen::Matrix2d& m0) {
  LsmResult result;
  result.position_in_base = c0;
  result.base_from_template_linear = m0;
  const int r = radius_, size = 2 * r + 1, n = size * size;
  cv::Mat t;
  if (!TemplatePatch(templ, p, r, &t)) {
    result.status = LsmResult::Status::kOutOfBounds;
    result.reason = "template patch does not fit in the template image";
    return result;
  }
  const int unknowns = options_.estimate_gain ? 8 : 7;  // 6 affine, [gain], offset.
  Eigen::MatrixXd design(n, unknowns);
  Eigen::VectorXd rhs(n);
  Eigen::Vector2d c = c0;
  Eigen::Matrix2d m = m0;
  double h1 = 1.0, h0 = 0.0;  // Template = h0 + h1 * base.
  const double inv_r = 1.0 / r;
  Eigen::VectorXd residual;
  Eigen::MatrixXd normal;
  result.status = LsmResult::Status::kNotConverged;
  bool full = options_.translation_only_iterations == 0 && options_.estimate_affine;
  for (int it = 1; it <= options_.max_iterations; ++it) {
    result.iterations = it;
    // One pixel wider than the window for the central-difference gradients (Gruen: the
    // gradients of the re-sampled search patch, recomputed every iteration).
    if (!WarpPatch(base, c, m, r + 1, &warped_)) {
      result.status = LsmResult::Status::kOutOfBounds;
      result.reason = "the warped patch left the base image";
      return result;
    }
    for (int v = 0; v < size; ++v) {
      const float* up = warped_.ptr<float>(v) + 1;
      const float* mid = warped_.ptr<float>(v + 1) + 1;
      const float* down = warped_.ptr<float>(v + 2) + 1;
      const float* tv = t.ptr<float>(v + 1) + 1;
      const double yn = (v - r) * inv_r;
      for (int u = 0; u < size; ++u) {
        const double xn = (u - r) * inv_r;
        const double gx = h1 * 0.5 * (mid[u + 1] - mid[u - 1]);
        const double gy = h1 * 0.5 * (down[u] - up[u]);
        const int i = v * size + u;
        design(i, 0) = gx;
        design(i, 1) = xn * gx;
        design(i, 2) = yn * gx;
        design(i, 3) = gy;
        design(i, 4) = xn * gy;
        design(i, 5) = yn * gy;
        if (unknowns == 8) design(i, 6) = mid[u];
        design(i, unknowns - 1) = 1.0;
        rhs(i) = tv[u] - h0 - h1 * mid[u];
      }
    }
    if (it == 1) {
      result.condition = NormalisedCondition(design.leftCols(6));
      if (result.condition == 0.0) {
        result.status = LsmResult::Status::kLowTexture;
        result.reason = "flat patch: zero gradient";
        return result;
      }
      if (result.condition > options_.max_condition) {
        result.status = LsmResult::Status::kIllConditioned;
        result.reason =
            Describe("condition number", result.condition, "above", options_.max_condition);
        return result;
      }
    }
    normal.noalias() = design.transpose() * design;
    const Eigen::VectorXd delta = SolveNormal(normal, design.transpose() * rhs, full);
    residual = rhs - design * delta;
    // Forward composition: w(x) <- w(x + d + D x).
    const Eigen::Vector2d d(delta(0), delta(3));
    Eigen::Matrix2d lin;
    lin << delta(1) * inv_r, delta(2) * inv_r, delta(4) * inv_r, delta(5) * inv_r;
    c = c + m * d;
    m = m * (Eigen::Matrix2d::Identity() + lin);
    if (unknowns == 8) h1 += delta(6);
    h0 += delta(unknowns - 1);
    if (CheckDivergence(options_, c0, c, m0, m, 1.0 / h1, &result)) return result;
    if (Settle(options_, CornerMotion(d, lin, r), it, &full)) {
      result.status = LsmResult::Status::kConverged;
      break;
    }
  }
  result.position_in_base = c;
  result.base_from_template_linear = m;
  result.gain = 1.0 / h1;
  result.residual_rms = std::sqrt(residual.squaredNorm() / residual.size());
  result.position_sigma_px = PositionSigma(normal, residual.squaredNorm(), n - unknowns, m);
  if (result.status == LsmResult::Status::kNotConverged) {
    result.reason = "still moving after max_iterations";
  } else if (!(result.position_sigma_px <= options_.max_position_sigma_px)) {
    result.status = LsmResult::Status::kLowTexture;
    result.reason = Describe("position sigma", result.position_sigma_px, "px above",
                             options_.max_position_sigma_px);
  }
  return result;
}

}  // namespace irmosaic
