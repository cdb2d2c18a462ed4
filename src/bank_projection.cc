#include "bank_projection.h"

#include <opencv2/core/hal/intrin.hpp>

#include "simd_dispatch.h"

#if defined(__x86_64__)
#include <immintrin.h>
#endif

namespace irmosaic::bank {
namespace {

constexpr int kLanes = 8;

// The fixed reduction of 8 lane sums and the tail's sum (see bank_projection.h).
inline double Finish(const float* lanes, float tail) {
  return static_cast<double>(((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) +
                             ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7])) + tail);
}

// The remaining i (n - n % 8 .. n - 1) of row r and column c, in order.
inline float Tail(const float* row, const float* column, int from, int n) {
  float sum = 0.0f;
  for (int i = from; i < n; ++i) sum += row[i] * column[i];
  return sum;
}

template <int K>
void ProjectScalarK(const float* bank, int rows, int n, const float* columns, double* out,
                    int out_stride) {
  const int body = n - n % kLanes;
  for (int r = 0; r < rows; ++r) {
    const float* row = bank + static_cast<size_t>(r) * n;
    for (int k = 0; k < K; ++k) {
      const float* column = columns + static_cast<size_t>(k) * n;
      float lanes[kLanes] = {};
      for (int i = 0; i < body; i += kLanes) {
        for (int l = 0; l < kLanes; ++l) lanes[l] += row[i + l] * column[i + l];
      }
      out[k * out_stride + r] = Finish(lanes, Tail(row, column, body, n));
    }
  }
}

template <int K>
void ProjectBaseline(const float* bank, int rows, int n, const float* columns, double* out,
                     int out_stride) {
#if CV_SIMD128
  const int body = n - n % kLanes;
  for (int r = 0; r < rows; ++r) {
    const float* row = bank + static_cast<size_t>(r) * n;
    cv::v_float32x4 low[K], high[K];
    for (int k = 0; k < K; ++k) low[k] = high[k] = cv::v_setzero_f32();
    for (int i = 0; i < body; i += kLanes) {
      const cv::v_float32x4 b0 = cv::v_load(row + i), b1 = cv::v_load(row + i + 4);
      for (int k = 0; k < K; ++k) {
        const float* column = columns + static_cast<size_t>(k) * n + i;
        low[k] = low[k] + b0 * cv::v_load(column);
        high[k] = high[k] + b1 * cv::v_load(column + 4);
      }
    }
    for (int k = 0; k < K; ++k) {
      float lanes[kLanes];
      cv::v_store(lanes, low[k]);
      cv::v_store(lanes + 4, high[k]);
      out[k * out_stride + r] =
          Finish(lanes, Tail(row, columns + static_cast<size_t>(k) * n, body, n));
    }
  }
#else
  ProjectScalarK<K>(bank, rows, n, columns, out, out_stride);
#endif
}

#if defined(__x86_64__)
template <int K>
__attribute__((target("avx2"))) void ProjectAvx2(const float* bank, int rows, int n,
                                                 const float* columns, double* out,
                                                 int out_stride) {
  const int body = n - n % kLanes;
  for (int r = 0; r < rows; ++r) {
    const float* row = bank + static_cast<size_t>(r) * n;
    __m256 acc[K];
    for (int k = 0; k < K; ++k) acc[k] = _mm256_setzero_ps();
    for (int i = 0; i < body; i += kLanes) {
      const __m256 b = _mm256_loadu_ps(row + i);
      for (int k = 0; k < K; ++k) {
        // Multiply, then add: no fused multiply-add, so the SSE2 path's results.
        acc[k] = _mm256_add_ps(
            acc[k], _mm256_mul_ps(b, _mm256_loadu_ps(columns + static_cast<size_t>(k) * n + i)));
      }
    }
    for (int k = 0; k < K; ++k) {
      float lanes[kLanes];
      _mm256_storeu_ps(lanes, acc[k]);
      out[k * out_stride + r] =
          Finish(lanes, Tail(row, columns + static_cast<size_t>(k) * n, body, n));
    }
  }
}
#endif

}  // namespace

void Project(const float* bank, int rows, int n, const float* columns, int k, double* out,
             int out_stride) {
  CV_Assert(k == 1 || k == 7);
#if defined(__x86_64__)
  if (simd::Avx2()) {
    if (k == 1) {
      ProjectAvx2<1>(bank, rows, n, columns, out, out_stride);
    } else {
      ProjectAvx2<7>(bank, rows, n, columns, out, out_stride);
    }
    return;
  }
#endif
  if (k == 1) {
    ProjectBaseline<1>(bank, rows, n, columns, out, out_stride);
  } else {
    ProjectBaseline<7>(bank, rows, n, columns, out, out_stride);
  }
}

void ProjectScalar(const float* bank, int rows, int n, const float* columns, int k, double* out,
                   int out_stride) {
  CV_Assert(k == 1 || k == 7);
  if (k == 1) {
    ProjectScalarK<1>(bank, rows, n, columns, out, out_stride);
  } else {
    ProjectScalarK<7>(bank, rows, n, columns, out, out_stride);
  }
}

}  // namespace irmosaic::bank
