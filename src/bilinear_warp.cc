// Bilinear projective sampling for the simulator (see bilinear_warp.h).
#include "bilinear_warp.h"

#include <algorithm>
#include <opencv2/core/hal/intrin.hpp>
#include <vector>

namespace irmosaic::sim {

namespace {

template <bool kAdd>
void Warp(const cv::Mat& src, const cv::Matx33d& m, cv::Size size, float add_scale, cv::Mat* dst) {
  CV_Assert(src.type() == CV_32FC1 && !src.empty() && dst->type() == CV_32FC1 &&
            dst->size() == size);
  const bool affine = m(2, 0) == 0.0 && m(2, 1) == 0.0 && m(2, 2) == 1.0;
  // Positions clamped to [0, size - 1 - eps] so that the right/lower neighbour always exists;
  // the eps moves a sample on the last row or column by 1e-3 px at most.
  CV_Assert(src.cols >= 2 && src.rows >= 2);
  const float max_u = static_cast<float>(src.cols - 1) * (1.0f - 1e-6f) - 1e-4f;
  const float max_v = static_cast<float>(src.rows - 1) * (1.0f - 1e-6f) - 1e-4f;
  const int stride = static_cast<int>(src.step1());
  const float* base = src.ptr<float>(0);
  // Per row: offsets and fractions of the sample positions (four at a time), then the gather.
  thread_local std::vector<int> offsets;
  thread_local std::vector<float> fus, fvs;
  offsets.resize(size.width + 4);
  fus.resize(size.width + 4);
  fvs.resize(size.width + 4);
  for (int y = 0; y < size.height; ++y) {
    // Row start and per-column increments (positions are far below 2^20: float is exact enough).
    const float u0 = static_cast<float>(m(0, 1) * y + m(0, 2)), du = static_cast<float>(m(0, 0));
    const float v0 = static_cast<float>(m(1, 1) * y + m(1, 2)), dv = static_cast<float>(m(1, 0));
    const float w0 = static_cast<float>(m(2, 1) * y + m(2, 2)), dw = static_cast<float>(m(2, 0));
    int x = 0;
#if CV_SIMD128
    {
      const cv::v_float32x4 step(0.0f, 1.0f, 2.0f, 3.0f), zero = cv::v_setzero_f32();
      const cv::v_float32x4 vmax_u = cv::v_setall_f32(max_u), vmax_v = cv::v_setall_f32(max_v);
      const cv::v_float32x4 one = cv::v_setall_f32(1.0f);
      const cv::v_int32x4 vstride = cv::v_setall_s32(stride);
      for (; x + 4 <= size.width; x += 4) {
        const cv::v_float32x4 xs = cv::v_setall_f32(static_cast<float>(x)) + step;
        cv::v_float32x4 u = cv::v_setall_f32(u0) + xs * cv::v_setall_f32(du);
        cv::v_float32x4 v = cv::v_setall_f32(v0) + xs * cv::v_setall_f32(dv);
        if (!affine) {
          const cv::v_float32x4 inv_w = one / (cv::v_setall_f32(w0) + xs * cv::v_setall_f32(dw));
          u = u * inv_w;
          v = v * inv_w;
        }
        u = cv::v_min(cv::v_max(u, zero), vmax_u);
        v = cv::v_min(cv::v_max(v, zero), vmax_v);
        const cv::v_int32x4 iu = cv::v_trunc(u), iv = cv::v_trunc(v);  // u, v >= 0: floor
        cv::v_store(fus.data() + x, u - cv::v_cvt_f32(iu));
        cv::v_store(fvs.data() + x, v - cv::v_cvt_f32(iv));
        cv::v_store(offsets.data() + x, iv * vstride + iu);
      }
    }
#endif
    for (; x < size.width; ++x) {
      float u = u0 + du * x, v = v0 + dv * x;
      if (!affine) {
        const float inv_w = 1.0f / (w0 + dw * x);
        u *= inv_w;
        v *= inv_w;
      }
      u = u >= 0.0f ? std::min(u, max_u) : 0.0f;  // NaN -> 0, as the SIMD path's max
      v = v >= 0.0f ? std::min(v, max_v) : 0.0f;
      const int iu = static_cast<int>(u), iv = static_cast<int>(v);
      fus[x] = u - static_cast<float>(iu);
      fvs[x] = v - static_cast<float>(iv);
      offsets[x] = iv * stride + iu;
    }
    float* out = dst->ptr<float>(y);
    for (x = 0; x < size.width; ++x) {
      const float* p = base + offsets[x];
      const float fu = fus[x];
      const float a = p[0] + fu * (p[1] - p[0]);
      const float b = p[stride] + fu * (p[stride + 1] - p[stride]);
      const float value = a + fvs[x] * (b - a);
      if constexpr (kAdd) {
        out[x] += add_scale * value;
      } else {
        out[x] = value;
      }
    }
  }
}

}  // namespace

void WarpBilinear(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Size size,
                  cv::Mat* dst) {
  dst->create(size, CV_32F);
  Warp<false>(src, src_from_dst, size, 0.0f, dst);
}

void AddWarpBilinear(const cv::Mat& src, const cv::Matx33d& src_from_dst, float scale,
                     cv::Mat* dst) {
  Warp<true>(src, src_from_dst, dst->size(), scale, dst);
}

}  // namespace irmosaic::sim
