#include "corner_response.h"

#include <cmath>
#include <opencv2/imgproc.hpp>

#include "buffer_view.h"

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace irmosaic::corner {
namespace {

// Row index i of an n-row image with BORDER_REFLECT_101 (|i| < n).
inline int Reflect101(int i, int n) { return i < 0 ? -i : (i >= n ? 2 * n - 2 - i : i); }

// dst[x] += src[x], x < n.
inline void AddRow(float* dst, const float* src, int n) {
  int x = 0;
#if defined(__SSE2__)
  for (; x + 4 <= n; x += 4) {
    _mm_storeu_ps(dst + x, _mm_add_ps(_mm_loadu_ps(dst + x), _mm_loadu_ps(src + x)));
  }
#endif
  for (; x < n; ++x) dst[x] += src[x];
}

// The Sobel derivatives of padded rows up / mid / down (each cols + 2 wide) into the products.
void Products(const float* up, const float* mid, const float* down, int cols, float scale,
              float* xx, float* xy, float* yy) {
  int x = 0;
#if defined(__SSE2__)
  const __m128 s = _mm_set1_ps(scale), two = _mm_set1_ps(2.0f);
  for (; x + 4 <= cols; x += 4) {
    const __m128 u0 = _mm_loadu_ps(up + x), u2 = _mm_loadu_ps(up + x + 2);
    const __m128 m0 = _mm_loadu_ps(mid + x), m2 = _mm_loadu_ps(mid + x + 2);
    const __m128 d0 = _mm_loadu_ps(down + x), d1 = _mm_loadu_ps(down + x + 1),
                 d2 = _mm_loadu_ps(down + x + 2);
    const __m128 u1 = _mm_loadu_ps(up + x + 1);
    const __m128 dx = _mm_mul_ps(_mm_add_ps(_mm_add_ps(_mm_sub_ps(u2, u0), _mm_sub_ps(d2, d0)),
                                            _mm_mul_ps(two, _mm_sub_ps(m2, m0))),
                                 s);
    const __m128 dy = _mm_mul_ps(_mm_add_ps(_mm_add_ps(_mm_sub_ps(d0, u0), _mm_sub_ps(d2, u2)),
                                            _mm_mul_ps(two, _mm_sub_ps(d1, u1))),
                                 s);
    _mm_storeu_ps(xx + x, _mm_mul_ps(dx, dx));
    _mm_storeu_ps(xy + x, _mm_mul_ps(dx, dy));
    _mm_storeu_ps(yy + x, _mm_mul_ps(dy, dy));
  }
#endif
  for (; x < cols; ++x) {
    const float dx =
        (((up[x + 2] - up[x]) + (down[x + 2] - down[x])) + 2.0f * (mid[x + 2] - mid[x])) * scale;
    const float dy =
        (((down[x] - up[x]) + (down[x + 2] - up[x + 2])) + 2.0f * (down[x + 1] - up[x + 1])) *
        scale;
    xx[x] = dx * dx;
    xy[x] = dx * dy;
    yy[x] = dy * dy;
  }
}

// The response of one row from the block's column sums, each extended by `half` reflected
// values on both sides (cols + 2 half wide).
void ResponseRow(const float* sxx, const float* sxy, const float* syy, int cols, int block,
                 float* out) {
  int x = 0;
#if defined(__SSE2__)
  const __m128 half = _mm_set1_ps(0.5f);
  for (; x + 4 <= cols; x += 4) {
    __m128 a = _mm_loadu_ps(sxx + x), b = _mm_loadu_ps(sxy + x), c = _mm_loadu_ps(syy + x);
    for (int k = 1; k < block; ++k) {
      a = _mm_add_ps(a, _mm_loadu_ps(sxx + x + k));
      b = _mm_add_ps(b, _mm_loadu_ps(sxy + x + k));
      c = _mm_add_ps(c, _mm_loadu_ps(syy + x + k));
    }
    a = _mm_mul_ps(a, half);
    c = _mm_mul_ps(c, half);
    const __m128 d = _mm_sub_ps(a, c);
    _mm_storeu_ps(out + x, _mm_sub_ps(_mm_add_ps(a, c),
                                      _mm_sqrt_ps(_mm_add_ps(_mm_mul_ps(d, d), _mm_mul_ps(b, b)))));
  }
#endif
  for (; x < cols; ++x) {
    float a = sxx[x], b = sxy[x], c = syy[x];
    for (int k = 1; k < block; ++k) a += sxx[x + k], b += sxy[x + k], c += syy[x + k];
    a *= 0.5f;
    c *= 0.5f;
    out[x] = (a + c) - std::sqrt((a - c) * (a - c) + b * b);
  }
}

}  // namespace

void MinEigenResponse(const cv::Mat& src, int block_size, cv::Mat* response) {
  CV_Assert(src.type() == CV_32FC1 && block_size >= 3 && block_size % 2 == 1);
  const int rows = src.rows, cols = src.cols, half = block_size / 2;
  if (rows < block_size + 2 || cols < block_size + 2) {
    cv::cornerMinEigenVal(src, *response, block_size, 3);
    return;
  }
  response->create(src.size(), CV_32F);
  // Per thread, grown to the largest image seen: no allocation per call once warm.
  thread_local cv::Mat padded_backing, products_backing, sums_backing;
  cv::Mat padded = BufferView(&padded_backing, cv::Size(cols + 2, rows + 2), CV_32F);
  cv::copyMakeBorder(src, padded, 1, 1, 1, 1, cv::BORDER_REFLECT_101 | cv::BORDER_ISOLATED);
  // The three products, one image each, stacked.
  cv::Mat products = BufferView(&products_backing, cv::Size(cols, 3 * rows), CV_32F);
  const float scale = static_cast<float>(1.0 / (4.0 * block_size));
  for (int y = 0; y < rows; ++y) {
    Products(padded.ptr<float>(y), padded.ptr<float>(y + 1), padded.ptr<float>(y + 2), cols, scale,
             products.ptr<float>(y), products.ptr<float>(rows + y),
             products.ptr<float>(2 * rows + y));
  }
  // Per output row: the block's column sums of each product, extended by `half` reflected
  // values on both sides, then summed across.
  const int wide = cols + 2 * half;
  cv::Mat sums = BufferView(&sums_backing, cv::Size(wide, 3), CV_32F);
  for (int y = 0; y < rows; ++y) {
    for (int p = 0; p < 3; ++p) {
      float* line = sums.ptr<float>(p) + half;
      const float* first = products.ptr<float>(p * rows + Reflect101(y - half, rows));
      std::copy(first, first + cols, line);
      for (int k = 1 - half; k <= half; ++k) {
        AddRow(line, products.ptr<float>(p * rows + Reflect101(y + k, rows)), cols);
      }
      for (int j = 0; j < half; ++j) {
        line[-1 - j] = line[1 + j];
        line[cols + j] = line[cols - 2 - j];
      }
    }
    ResponseRow(sums.ptr<float>(0), sums.ptr<float>(1), sums.ptr<float>(2), cols, block_size,
                response->ptr<float>(y));
  }
}

}  // namespace irmosaic::corner
