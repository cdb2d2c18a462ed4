// Bilinear projective resampling of 8- and 16-bit frames (see warp_bilinear.h).
#include "warp_bilinear.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>

#include "simd_dispatch.h"

#if defined(__x86_64__)
#include <immintrin.h>
#endif

namespace irmosaic::warp {
namespace {

// A row's map: X, Y, W = a * x + b for output column x (float; b folds in the row).
struct RowMap {
  float ax, bx, ay, by, aw, bw;
};

RowMap MapOfRow(const cv::Matx33d& m, int y) {
  return {static_cast<float>(m(0, 0)), static_cast<float>(m(0, 1) * y + m(0, 2)),
          static_cast<float>(m(1, 0)), static_cast<float>(m(1, 1) * y + m(1, 2)),
          static_cast<float>(m(2, 0)), static_cast<float>(m(2, 1) * y + m(2, 2))};
}

// One output pixel. The operations (and their order) are the AVX2 lanes': max/min written as
// the instructions behave (a NaN position goes to 0), truncation of a non-negative position,
// rounding to nearest even.
template <typename T>
inline T SamplePixel(const uint8_t* src, size_t step, int cols, int rows, const RowMap& r, int x) {
  const float fx = static_cast<float>(x);
  const float px = r.ax * fx + r.bx, py = r.ay * fx + r.by, pw = r.aw * fx + r.bw;
  const float inv = 1.0f / pw;
  float sx = px * inv, sy = py * inv;
  sx = sx > 0.0f ? sx : 0.0f;
  sy = sy > 0.0f ? sy : 0.0f;
  const float max_x = static_cast<float>(cols - 1), max_y = static_cast<float>(rows - 1);
  sx = sx < max_x ? sx : max_x;
  sy = sy < max_y ? sy : max_y;
  int ix = static_cast<int>(sx), iy = static_cast<int>(sy);
  ix = ix < cols - 2 ? ix : cols - 2;
  iy = iy < rows - 2 ? iy : rows - 2;
  const float tx = sx - static_cast<float>(ix), ty = sy - static_cast<float>(iy);
  const T* top = reinterpret_cast<const T*>(src + static_cast<size_t>(iy) * step) + ix;
  const T* bottom = reinterpret_cast<const T*>(src + static_cast<size_t>(iy + 1) * step) + ix;
  const float p00 = top[0], p01 = top[1], p10 = bottom[0], p11 = bottom[1];
  const float upper = p00 + (p01 - p00) * tx;
  const float lower = p10 + (p11 - p10) * tx;
  const float value = upper + (lower - upper) * ty;
  return static_cast<T>(static_cast<int>(std::nearbyint(value)));
}

template <typename T>
void WarpRowsScalar(const cv::Mat& src, const cv::Matx33d& m, cv::Mat* dst, int y0, int y1) {
  for (int y = y0; y < y1; ++y) {
    const RowMap r = MapOfRow(m, y);
    T* out = dst->ptr<T>(y);
    for (int x = 0; x < dst->cols; ++x)
      out[x] = SamplePixel<T>(src.data, src.step, src.cols, src.rows, r, x);
  }
}

#if defined(__x86_64__)
// The 32-bit words at byte offsets `offset` from `base`: one AVX2 gather instruction, or eight
// scalar loads put together (kEmulated). The same values either way; which is faster depends on
// the CPU (on the Intel Xeon of session 47 a gather took 25 cycles and the eight loads made the
// warp 1.45-1.55x faster; why its gathers are that slow was not established).
template <bool kEmulated>
__attribute__((target("avx2"))) inline __m256i Gather32(const int* base, __m256i offset) {
  if constexpr (kEmulated) {
    alignas(32) int at[8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(at), offset);
    const char* bytes = reinterpret_cast<const char*>(base);
    int v[8];
    for (int k = 0; k < 8; ++k) std::memcpy(&v[k], bytes + at[k], sizeof(int));
    return _mm256_setr_epi32(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7]);
  } else {
    return _mm256_i32gather_epi32(base, offset, 1);
  }
}

template <typename T, bool kEmulatedGather>
__attribute__((target("avx2"))) void WarpRowsAvx2(const cv::Mat& src, const cv::Matx33d& m,
                                                  cv::Mat* dst) {
  const int cols = src.cols, rows = src.rows;
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  const __m256 max_x = _mm256_set1_ps(static_cast<float>(cols - 1));
  const __m256 max_y = _mm256_set1_ps(static_cast<float>(rows - 1));
  const __m256i last_ix = _mm256_set1_epi32(cols - 2), last_iy = _mm256_set1_epi32(rows - 2);
  const __m256i step = _mm256_set1_epi32(static_cast<int>(src.step));
  const __m256i low16 = _mm256_set1_epi32(0xFFFF), low8 = _mm256_set1_epi32(0xFF);
  const __m256i lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const int* base = reinterpret_cast<const int*>(src.data);
  const int* below = reinterpret_cast<const int*>(src.data + src.step);
  const int* below_minus_2 = reinterpret_cast<const int*>(src.data + src.step - 2);
  for (int y = 0; y < dst->rows; ++y) {
    const RowMap r = MapOfRow(m, y);
    const __m256 ax = _mm256_set1_ps(r.ax), bx = _mm256_set1_ps(r.bx);
    const __m256 ay = _mm256_set1_ps(r.ay), by = _mm256_set1_ps(r.by);
    const __m256 aw = _mm256_set1_ps(r.aw), bw = _mm256_set1_ps(r.bw);
    T* out = dst->ptr<T>(y);
    int x = 0;
    for (; x + 8 <= dst->cols; x += 8) {
      const __m256 fx = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(x), lanes));
      const __m256 px = _mm256_add_ps(_mm256_mul_ps(ax, fx), bx);
      const __m256 py = _mm256_add_ps(_mm256_mul_ps(ay, fx), by);
      const __m256 pw = _mm256_add_ps(_mm256_mul_ps(aw, fx), bw);
      const __m256 inv = _mm256_div_ps(one, pw);
      __m256 sx = _mm256_mul_ps(px, inv), sy = _mm256_mul_ps(py, inv);
      sx = _mm256_min_ps(_mm256_max_ps(sx, zero), max_x);
      sy = _mm256_min_ps(_mm256_max_ps(sy, zero), max_y);
      const __m256i ix = _mm256_min_epi32(_mm256_cvttps_epi32(sx), last_ix);
      const __m256i iy = _mm256_min_epi32(_mm256_cvttps_epi32(sy), last_iy);
      const __m256 tx = _mm256_sub_ps(sx, _mm256_cvtepi32_ps(ix));
      const __m256 ty = _mm256_sub_ps(sy, _mm256_cvtepi32_ps(iy));
      __m256 p00, p01, p10, p11;
      if constexpr (sizeof(T) == 2) {
        // Byte offset of (ix, iy); one 32-bit gather per row reads the pixel and its right
        // neighbour (ix <= cols - 2, so both inside the row).
        const __m256i offset =
            _mm256_add_epi32(_mm256_mullo_epi32(iy, step), _mm256_add_epi32(ix, ix));
        const __m256i upper_pair = Gather32<kEmulatedGather>(base, offset);
        const __m256i lower_pair = Gather32<kEmulatedGather>(below, offset);
        p00 = _mm256_cvtepi32_ps(_mm256_and_si256(upper_pair, low16));
        p01 = _mm256_cvtepi32_ps(_mm256_srli_epi32(upper_pair, 16));
        p10 = _mm256_cvtepi32_ps(_mm256_and_si256(lower_pair, low16));
        p11 = _mm256_cvtepi32_ps(_mm256_srli_epi32(lower_pair, 16));
      } else {
        // 4 bytes per gather: the upper row's from the pixel on (bytes 0-1 are the pair; ix + 3
        // stays inside the buffer, a row follows), the lower row's from two bytes before it
        // (bytes 2-3; the last row's last pixel pair ends the buffer, nothing is read past it).
        const __m256i offset = _mm256_add_epi32(_mm256_mullo_epi32(iy, step), ix);
        const __m256i upper = Gather32<kEmulatedGather>(base, offset);
        const __m256i lower = Gather32<kEmulatedGather>(below_minus_2, offset);
        p00 = _mm256_cvtepi32_ps(_mm256_and_si256(upper, low8));
        p01 = _mm256_cvtepi32_ps(_mm256_and_si256(_mm256_srli_epi32(upper, 8), low8));
        p10 = _mm256_cvtepi32_ps(_mm256_and_si256(_mm256_srli_epi32(lower, 16), low8));
        p11 = _mm256_cvtepi32_ps(_mm256_srli_epi32(lower, 24));
      }
      const __m256 upper = _mm256_add_ps(p00, _mm256_mul_ps(_mm256_sub_ps(p01, p00), tx));
      const __m256 lower = _mm256_add_ps(p10, _mm256_mul_ps(_mm256_sub_ps(p11, p10), tx));
      const __m256 value = _mm256_add_ps(upper, _mm256_mul_ps(_mm256_sub_ps(lower, upper), ty));
      const __m256i rounded = _mm256_cvtps_epi32(value);
      // Pack to 16 bits (values are within [0, 65535]) and put the two halves together.
      const __m256i words = _mm256_packus_epi32(rounded, rounded);
      if constexpr (sizeof(T) == 2) {
        const __m256i packed = _mm256_permute4x64_epi64(words, 0x08);
        _mm_storeu_si128(reinterpret_cast<__m128i*>(out + x), _mm256_castsi256_si128(packed));
      } else {  // On to 8 bits (within [0, 255]): each half's first 4 bytes, side by side.
        const __m256i bytes = _mm256_packus_epi16(words, words);
        const __m256i packed =
            _mm256_permutevar8x32_epi32(bytes, _mm256_setr_epi32(0, 4, 0, 0, 0, 0, 0, 0));
        _mm_storel_epi64(reinterpret_cast<__m128i*>(out + x), _mm256_castsi256_si128(packed));
      }
    }
    for (; x < dst->cols; ++x) out[x] = SamplePixel<T>(src.data, src.step, cols, rows, r, x);
  }
}

template <bool kEmulatedGather>
void WarpAvx2(const cv::Mat& src, const cv::Matx33d& m, cv::Mat* dst) {
  if (src.depth() == CV_16U) {
    WarpRowsAvx2<uint16_t, kEmulatedGather>(src, m, dst);
  } else {
    WarpRowsAvx2<uint8_t, kEmulatedGather>(src, m, dst);
  }
}

// Which gather this CPU runs faster, measured once: an 8-bit oblique warp of 64 x 48 output
// pixels (sources in L1, as a frame's rows mostly are) by each path in turn, 9 rounds, the
// fastest round of each. Both give the same output, so a wrong choice costs time only.
// IRMOSAIC_WARP_GATHER=hardware or emulated in the environment skips the measurement.
GatherPath MeasureGatherPath() {
  const char* forced = std::getenv("IRMOSAIC_WARP_GATHER");
  if (forced != nullptr && std::strcmp(forced, "hardware") == 0) return GatherPath::kHardware;
  if (forced != nullptr && std::strcmp(forced, "emulated") == 0) return GatherPath::kEmulated;
  cv::Mat src(96, 128, CV_8U), dst(48, 64, CV_8U);
  for (int y = 0; y < src.rows; ++y)
    for (int x = 0; x < src.cols; ++x) src.at<uint8_t>(y, x) = static_cast<uint8_t>(x * 7 + y * 3);
  const cv::Matx33d m(0.93, 0.31, 9.5, -0.27, 1.04, 30.25, 0.0007, 0.0002, 1.0);
  using Clock = std::chrono::steady_clock;
  auto time_one = [&](auto warp) {
    const auto t0 = Clock::now();
    for (int k = 0; k < 8; ++k) warp(src, m, &dst);
    return std::chrono::duration<double>(Clock::now() - t0).count();
  };
  double hardware = std::numeric_limits<double>::infinity(), emulated = hardware;
  for (int round = 0; round < 9; ++round) {
    hardware = std::min(hardware, time_one(WarpAvx2<false>));
    emulated = std::min(emulated, time_one(WarpAvx2<true>));
  }
  return emulated < hardware ? GatherPath::kEmulated : GatherPath::kHardware;
}

GatherPath ChosenGatherPath() {
  static const GatherPath path = MeasureGatherPath();
  return path;
}
#endif

bool Supported(const cv::Mat& src, const cv::Mat* dst) {
  return (src.type() == CV_16UC1 || src.type() == CV_8UC1) && src.cols >= 2 && src.rows >= 2 &&
         dst != nullptr && dst->type() == src.type() &&
         static_cast<double>(src.step) * src.rows < std::numeric_limits<int>::max();
}

}  // namespace

bool WarpBilinear(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Mat* dst) {
  if (!Supported(src, dst)) return false;
#if defined(__x86_64__)
  if (simd::Avx2()) {
    if (ChosenGatherPath() == GatherPath::kEmulated) {
      WarpAvx2<true>(src, src_from_dst, dst);
    } else {
      WarpAvx2<false>(src, src_from_dst, dst);
    }
    return true;
  }
#endif
  return WarpBilinearScalar(src, src_from_dst, dst);
}

bool WarpBilinearAvx2(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Mat* dst,
                      GatherPath gather) {
#if defined(__x86_64__)
  if (!Supported(src, dst) || !simd::Avx2()) return false;
  if (gather == GatherPath::kEmulated) {
    WarpAvx2<true>(src, src_from_dst, dst);
  } else {
    WarpAvx2<false>(src, src_from_dst, dst);
  }
  return true;
#else
  (void)src, (void)src_from_dst, (void)dst, (void)gather;
  return false;
#endif
}

const char* GatherPathName() {
#if defined(__x86_64__)
  if (simd::Avx2()) return ChosenGatherPath() == GatherPath::kEmulated ? "emulated" : "hardware";
#endif
  return "none";
}

bool WarpBilinearScalar(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Mat* dst) {
  if (!Supported(src, dst)) return false;
  if (src.depth() == CV_16U) {
    WarpRowsScalar<uint16_t>(src, src_from_dst, dst, 0, dst->rows);
  } else {
    WarpRowsScalar<uint8_t>(src, src_from_dst, dst, 0, dst->rows);
  }
  return true;
}

}  // namespace irmosaic::warp
