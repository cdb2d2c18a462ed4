// Masked SCD template matching in the frequency domain (PAPER_NOTES.md, "SCD").
#include "irmosaic/scd.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <opencv2/core/hal/intrin.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <type_traits>
#include <vector>

namespace irmosaic {
namespace {

using Status = ScdResult::Status;

bool IsSupportedImage(const cv::Mat& image) {
  const int depth = image.depth();
  return image.dims == 2 && image.channels() == 1 &&
         (depth == CV_8U || depth == CV_16U || depth == CV_32F);
}

// Empty, or CV_8U one channel of the image's size.
bool IsSupportedMask(const cv::Mat& mask, const cv::Mat& image) {
  return mask.empty() || (mask.type() == CV_8UC1 && mask.size() == image.size());
}

#if CV_SIMD128
// Four bytes widened to four 32-bit lanes. OpenCV's v_load_expand_q reads its 4 bytes through an
// int pointer, undefined (UBSan: misaligned load) at the unaligned addresses a mask row gives;
// an aligned copy keeps it defined and compiles to the same load.
inline cv::v_uint32x4 LoadExpand4(const uint8_t* p) {
  uint32_t word;
  std::memcpy(&word, p, sizeof word);
  return cv::v_load_expand_q(reinterpret_cast<const uchar*>(&word));
}
#endif

// 1D full convolution of two small kernels.
std::vector<double> Convolve(const std::vector<double>& a, const std::vector<double>& b) {
  std::vector<double> out(a.size() + b.size() - 1, 0.0);
  for (size_t i = 0; i < a.size(); ++i) {
    for (size_t j = 0; j < b.size(); ++j) out[i + j] += a[i] * b[j];
  }
  return out;
}

double SumOfSquares(const std::vector<double>& v) {
  double s = 0.0;
  for (double x : v) s += x * x;
  return s;
}

// Immerkaer (1996) noise std of a float image: sqrt(pi/2)/6 * mean |I * N| over valid pixels
// (N = [1 -2 1; -2 4 -2; 1 -2 1], blind to planes and linear ramps). Every other row is enough.
double EstimateNoiseStd(const cv::Mat& image_f32, const cv::Mat& valid_u8) {
  double sum = 0.0;
  int64_t count = 0;
  for (int y = 1; y + 1 < image_f32.rows; y += 2) {
    const float* a = image_f32.ptr<float>(y - 1);
    const float* b = image_f32.ptr<float>(y);
    const float* c = image_f32.ptr<float>(y + 1);
    const uint8_t* m = valid_u8.ptr<uint8_t>(y);
    float row_sum = 0.0f;
    int row_count = 0;
    int x = 1;
#if CV_SIMD128
    // The scalar loop below, four pixels at a time.
    const cv::v_float32x4 zero = cv::v_setzero_f32(), one = cv::v_setall_f32(1.0f);
    const cv::v_float32x4 two = cv::v_setall_f32(2.0f), four = cv::v_setall_f32(4.0f);
    cv::v_float32x4 vsum = zero, vcount = zero;
    for (; x + 5 <= image_f32.cols; x += 4) {
      const cv::v_float32x4 l = (cv::v_load(a + x - 1) + cv::v_load(a + x + 1) +
                                 cv::v_load(c + x - 1) + cv::v_load(c + x + 1)) -
                                two * (cv::v_load(a + x) + cv::v_load(c + x) +
                                       cv::v_load(b + x - 1) + cv::v_load(b + x + 1)) +
                                four * cv::v_load(b + x);
      const cv::v_float32x4 w = cv::v_select(
          cv::v_cvt_f32(cv::v_reinterpret_as_s32(LoadExpand4(m + x))) != zero, one, zero);
      vsum += w * cv::v_abs(l);
      vcount += w;
    }
    row_sum = cv::v_reduce_sum(vsum);
    row_count = static_cast<int>(cv::v_reduce_sum(vcount));
#endif
    for (; x + 1 < image_f32.cols; ++x) {
      const float l = (a[x - 1] + a[x + 1] + c[x - 1] + c[x + 1]) -
                      2.0f * (a[x] + c[x] + b[x - 1] + b[x + 1]) + 4.0f * b[x];
      const float w = m[x] ? 1.0f : 0.0f;
      row_sum += w * std::abs(l);
      row_count += m[x] ? 1 : 0;
    }
    sum += row_sum;
    count += row_count;
  }
  return count > 0 ? std::sqrt(CV_PI / 2.0) / 6.0 * sum / static_cast<double>(count) : 0.0;
}

// DFT length >= n that OpenCV transforms fastest: among the 2-3-5-smooth lengths some are much
// slower than a longer one (measured, one thread, OpenCV 4.6, n x 120 and 120 x n transforms:
// 90: 78 us, 96: 73; 120: 97, 128: 97; 135: 148, 144: 116), so the table keeps only lengths
// that no longer one beats; past it, multiples of 8 (odd lengths were the slow ones).
int FastDftSize(int n) {
  static constexpr int kFast[] = {32,  36,  40,  48,  50,  54,  64,  72,  80,  96,  100, 108,
                                  128, 144, 160, 162, 192, 200, 240, 256, 288, 320, 324};
  if (n < kFast[0]) return cv::getOptimalDFTSize(n);
  for (int m : kFast) {
    if (m >= n) return m;
  }
  int m = (n + 7) / 8 * 8;
  while (cv::getOptimalDFTSize(m) != m) m += 8;
  return m;
}

// Sub-pixel position of a peak from its two neighbours (c the peak value); in [-0.5, 0.5].
double ParabolaDelta(double left, double centre, double right) {
  const double curvature = left - 2.0 * centre + right;
  if (!(curvature < 0.0)) return 0.0;
  return std::clamp(0.5 * (left - right) / curvature, -0.5, 0.5);
}

double RefineAxis(ScdSubpixel mode, double left, double centre, double right) {
  if (mode == ScdSubpixel::kGaussian && left > 0 && centre > 0 && right > 0) {
    return ParabolaDelta(std::log(left), std::log(centre), std::log(right));
  }
  return ParabolaDelta(left, centre, right);
}

std::string Describe(const cv::Mat& m) {
  std::ostringstream s;
  s << m.cols << "x" << m.rows << " type " << m.type() << " channels " << m.channels();
  return s.str();
}

}  // namespace

const char* ToString(ScdResult::Status status) {
  switch (status) {
    case Status::kOk:
      return "ok";
    case Status::kTooLittleOverlap:
      return "too little overlap";
    case Status::kAmbiguous:
      return "ambiguous";
    case Status::kFlat:
      return "flat";
    case Status::kBadInput:
      return "bad input";
  }
  return "unknown";
}

bool ScdOptions::IsValid(std::string* error) const {
  auto fail = [error](const std::string& why) {
    if (error) *error = why;
    return false;
  };
  if (!(gradient_sigma_px >= 0.0 && gradient_sigma_px <= 20.0)) {
    return fail("gradient_sigma_px must be in [0, 20]");
  }
  if (!(min_overlap_fraction >= 0.0 && min_overlap_fraction <= 1.0)) {
    return fail("min_overlap_fraction must be in [0, 1]");
  }
  if (!(noise_floor_sigmas >= 0.0 && noise_floor_sigmas <= 100.0)) {
    return fail("noise_floor_sigmas must be in [0, 100]");
  }
  if (!(min_oriented_fraction >= 0.0 && min_oriented_fraction <= 1.0)) {
    return fail("min_oriented_fraction must be in [0, 1]");
  }
  if (!(min_peak_ratio >= 1.0 && min_peak_ratio < 1e3)) {
    return fail("min_peak_ratio must be in [1, 1000)");
  }
  if (!(peak_exclusion_px >= 1.0 && peak_exclusion_px <= 1e3)) {
    return fail("peak_exclusion_px must be in [1, 1000]");
  }
  if (pyramid_factor != 1 && pyramid_factor != 2 && pyramid_factor != 4 && pyramid_factor != 8) {
    return fail("pyramid_factor must be 1, 2, 4 or 8");
  }
  if (!(coarse_gradient_sigma_px >= 0.0 && coarse_gradient_sigma_px <= 20.0)) {
    return fail("coarse_gradient_sigma_px must be in [0, 20]");
  }
  if (fine_template_step != 1 && fine_template_step != 2) {
    return fail("fine_template_step must be 1 or 2");
  }
  if (!(subpixel_refit_max_px >= 0.0 && subpixel_refit_max_px <= 2.0)) {
    return fail("subpixel_refit_max_px must be in [0, 2]");
  }
  if (!(magnitude_weight_cap >= 0.0 && magnitude_weight_cap <= 100.0)) {
    return fail("magnitude_weight_cap must be in [0, 100]");
  }
  if (!(max_search_radius_px > 0.0 && max_search_radius_px <= 1e5)) {
    return fail("max_search_radius_px must be in (0, 1e5]");
  }
  return true;
}

namespace {

// Keys (a = -0.5) cubic weights of the samples at -1, 0, 1, 2 for a position t in [0, 1).
cv::Mat CubicWeights(double t) {
  const double a = -0.5;
  auto w = [a](double x) {
    x = std::abs(x);
    return x <= 1.0  ? ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
           : x < 2.0 ? ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
                     : 0.0;
  };
  return (cv::Mat_<float>(4, 1) << w(t + 1.0), w(t), w(1.0 - t), w(2.0 - t));
}

// The vertical pass of CubicShiftSampled: rows(k, j) = sum_i wy_i src(origin.y + step k +
// floor(shift_y) - 1 + i, origin.x - 3 + j) at the output rows only, on every column any
// horizontal shift of |shift.x| < 2 reads (j < step (count.width - 1) + 7), reads clamped to src.
// One vertical pass serves all the refit's shifts with the same shift_y.
void CubicRows(const cv::Mat& src, cv::Point origin, cv::Size count, int step, double shift_y,
               cv::Mat* rows) {
  const double fy = std::floor(shift_y);
  const cv::Mat ky = CubicWeights(shift_y - fy);
  const float wy[4] = {ky.at<float>(0), ky.at<float>(1), ky.at<float>(2), ky.at<float>(3)};
  const int c0 = origin.x - 3, r0 = origin.y + static_cast<int>(fy) - 1;
  const int tw = step * (count.width - 1) + 7;
  rows->create(count.height, tw, CV_32F);
  const int j_lo = std::clamp(-c0, 0, tw), j_hi = std::clamp(src.cols - c0, j_lo, tw);
  for (int y = 0; y < count.height; ++y) {
    const float* s[4];
    for (int k = 0; k < 4; ++k) {
      s[k] = src.ptr<float>(std::clamp(r0 + step * y + k, 0, src.rows - 1));
    }
    float* t = rows->ptr<float>(y);
    auto scalar = [&](int j) {
      const int col = std::clamp(c0 + j, 0, src.cols - 1);
      t[j] = wy[0] * s[0][col] + wy[1] * s[1][col] + wy[2] * s[2][col] + wy[3] * s[3][col];
    };
    int j = 0;
    for (; j < j_lo; ++j) scalar(j);
#if CV_SIMD128
    const cv::v_float32x4 w0 = cv::v_setall_f32(wy[0]), w1 = cv::v_setall_f32(wy[1]);
    const cv::v_float32x4 w2 = cv::v_setall_f32(wy[2]), w3 = cv::v_setall_f32(wy[3]);
    for (; j + 4 <= j_hi; j += 4) {
      const int col = c0 + j;
      cv::v_store(t + j, w0 * cv::v_load(s[0] + col) + w1 * cv::v_load(s[1] + col) +
                             w2 * cv::v_load(s[2] + col) + w3 * cv::v_load(s[3] + col));
    }
#endif
    for (; j < tw; ++j) scalar(j);
  }
}

// out(k) = src(origin + step k + shift) for k in [0, count) from the vertical pass `rows` of
// CubicRows at shift.y(): the horizontal four taps at the output columns only (step 1 or 2).
// Together the separable cubic (Keys) of CubicShift without OpenCV's per-call filter set-up.
void CubicColumns(const cv::Mat& rows, cv::Size count, int step, double shift_x, cv::Mat* out) {
  const double fx = std::floor(shift_x);
  const cv::Mat kx = CubicWeights(shift_x - fx);
  const float wx[4] = {kx.at<float>(0), kx.at<float>(1), kx.at<float>(2), kx.at<float>(3)};
  const int first = static_cast<int>(fx) + 2;  // column of tap 0 of output 0 in `rows`
  out->create(count, CV_32F);
  for (int y = 0; y < count.height; ++y) {
    const float* t = rows.ptr<float>(y) + first;
    float* o = out->ptr<float>(y);
    int x = 0;
#if CV_SIMD128
    const cv::v_float32x4 x0 = cv::v_setall_f32(wx[0]), x1 = cv::v_setall_f32(wx[1]);
    const cv::v_float32x4 x2 = cv::v_setall_f32(wx[2]), x3 = cv::v_setall_f32(wx[3]);
    if (step == 1) {
      for (; x + 4 <= count.width; x += 4) {
        cv::v_store(o + x, x0 * cv::v_load(t + x) + x1 * cv::v_load(t + x + 1) +
                               x2 * cv::v_load(t + x + 2) + x3 * cv::v_load(t + x + 3));
      }
    } else if (step == 2) {
      // Taps 2x + 0..3 of four outputs from two de-interleaved loads; the last reads t[2x + 9]
      // (x + 4 <= count.width), inside the row: first + 2 count.width + 1 < 2 count.width + 5.
      for (; x + 4 <= count.width; x += 4) {
        cv::v_float32x4 e0, o0, e2, o2;
        cv::v_load_deinterleave(t + 2 * x, e0, o0);
        cv::v_load_deinterleave(t + 2 * x + 2, e2, o2);
        cv::v_store(o + x, x0 * e0 + x1 * o0 + x2 * e2 + x3 * o2);
      }
    }
#endif
    for (; x < count.width; ++x) {
      const float* tx = t + step * x;
      o[x] = wx[0] * tx[0] + wx[1] * tx[1] + wx[2] * tx[2] + wx[3] * tx[3];
    }
  }
}

// *f32 = image as float, *valid = 255 where the mask (empty: all) is set and the sample is
// finite, else 0; invalid samples then hold the mean of the valid ones (0 if none), so that a
// mask edge is a small step. One pass (two with no-data), 16 pixels at a time.
void LoadValidFilled(const cv::Mat& image, const cv::Mat& mask, cv::Mat* f32, cv::Mat* valid) {
  if (image.depth() != CV_32F) {
    image.convertTo(*f32, CV_32F);  // 8 and 16 bit samples are finite; converted in place below
  } else {
    f32->create(image.size(), CV_32F);
  }
  const cv::Mat& src = image.depth() == CV_32F ? image : *f32;
  valid->create(image.size(), CV_8U);
  const int w = image.cols;
  double sum = 0.0;
  int64_t count = 0;
  for (int y = 0; y < image.rows; ++y) {
    const float* in = src.ptr<float>(y);
    const uint8_t* m = mask.empty() ? nullptr : mask.ptr<uint8_t>(y);
    float* out = f32->ptr<float>(y);
    uint8_t* ok = valid->ptr<uint8_t>(y);
    float row_sum = 0.0f;
    int row_count = 0;
    int x = 0;
#if CV_SIMD128
    const cv::v_uint32x4 exponent = cv::v_setall_u32(0x7f800000u), zero_u = cv::v_setzero_u32();
    const cv::v_uint32x4 all_u = cv::v_setall_u32(0xffffffffu);
    const cv::v_float32x4 zero = cv::v_setzero_f32(), one = cv::v_setall_f32(1.0f);
    cv::v_float32x4 vsum = zero, vcount = zero;
    for (; x + 16 <= w; x += 16) {
      cv::v_uint32x4 good[4];
      for (int k = 0; k < 4; ++k) {
        const cv::v_float32x4 v = cv::v_load(in + x + 4 * k);
        const cv::v_uint32x4 finite = (cv::v_reinterpret_as_u32(v) & exponent) != exponent;
        const cv::v_uint32x4 set = m ? LoadExpand4(m + x + 4 * k) != zero_u : all_u;
        good[k] = finite & set;
        cv::v_store(out + x + 4 * k, cv::v_select(cv::v_reinterpret_as_f32(finite), v, zero));
        const cv::v_float32x4 g = cv::v_reinterpret_as_f32(good[k]);
        vsum += cv::v_select(g, v, zero);
        vcount += cv::v_select(g, one, zero);
      }
      cv::v_store(ok + x, cv::v_pack(cv::v_pack(good[0], good[1]), cv::v_pack(good[2], good[3])));
    }
    row_sum = cv::v_reduce_sum(vsum);
    row_count = static_cast<int>(cv::v_reduce_sum(vcount));
#endif
    for (; x < w; ++x) {
      const float v = in[x];
      const bool finite = std::abs(v) <= std::numeric_limits<float>::max();  // NaN: false
      const bool good = finite && (!m || m[x] != 0);
      out[x] = finite ? v : 0.0f;
      ok[x] = good ? 255 : 0;
      row_sum += good ? v : 0.0f;
      row_count += good;
    }
    sum += row_sum;
    count += row_count;
  }
  if (count == static_cast<int64_t>(image.total())) return;
  const float fill = count > 0 ? static_cast<float>(sum / static_cast<double>(count)) : 0.0f;
  for (int y = 0; y < image.rows; ++y) {
    float* out = f32->ptr<float>(y);
    const uint8_t* ok = valid->ptr<uint8_t>(y);
    int x = 0;
#if CV_SIMD128
    const cv::v_uint32x4 zero_u = cv::v_setzero_u32();
    const cv::v_float32x4 fill4 = cv::v_setall_f32(fill);
    for (; x + 4 <= w; x += 4) {
      const cv::v_float32x4 g = cv::v_reinterpret_as_f32(LoadExpand4(ok + x) != zero_u);
      cv::v_store(out + x, cv::v_select(g, cv::v_load(out + x), fill4));
    }
#endif
    for (; x < w; ++x) {
      if (!ok[x]) out[x] = fill;
    }
  }
}

// Pixels where both CV_8U masks a and b (same size; pass a twice for one mask) are set: their
// count and, if box is given, their bounding box (empty when none). One pass, no temporary,
// 16 pixels at a time (instead of bitwise_and, then countNonZero or boundingRect).
void BothSet(const cv::Mat& a, const cv::Mat& b, int64_t* count, cv::Rect* box) {
  const int w = a.cols;
  int64_t n = 0;
  int x_lo = w, x_hi = -1, y_lo = a.rows, y_hi = -1;
  for (int y = 0; y < a.rows; ++y) {
    const uint8_t* pa = a.ptr<uint8_t>(y);
    const uint8_t* pb = b.ptr<uint8_t>(y);
    int64_t row_n = 0;
    int first = -1, last = -1;  // first and last set column of the row
    int x = 0;
#if CV_SIMD128
    const cv::v_uint8x16 zero = cv::v_setzero_u8();
    auto sum = [](const cv::v_uint8x16& v) {
      cv::v_uint16x8 lo, hi;
      cv::v_expand(v, lo, hi);
      return static_cast<int64_t>(cv::v_reduce_sum(lo + hi));
    };
    cv::v_uint8x16 acc = zero;
    int blocks = 0, first_block = -1, last_block = -1;
    for (; x + 16 <= w; x += 16) {
      const cv::v_uint8x16 set = cv::v_min(cv::v_load(pa + x), cv::v_load(pb + x)) != zero;
      if (box && cv::v_check_any(set)) {
        if (first_block < 0) first_block = x;
        last_block = x;
      }
      acc = cv::v_sub_wrap(acc, set);  // +1 where set (set lanes are 0xff)
      if (++blocks == 255) {
        row_n += sum(acc);
        acc = zero;
        blocks = 0;
      }
    }
    row_n += sum(acc);
    if (first_block >= 0) {
      first = first_block;
      while (!(pa[first] && pb[first])) ++first;
      last = last_block + 15;
      while (!(pa[last] && pb[last])) --last;
    }
#endif
    for (; x < w; ++x) {
      if (pa[x] && pb[x]) {
        ++row_n;
        if (first < 0) first = x;
        last = x;
      }
    }
    if (row_n > 0) {
      y_lo = std::min(y_lo, y);
      y_hi = y;
      x_lo = std::min(x_lo, first);
      x_hi = std::max(x_hi, last);
    }
    n += row_n;
  }
  *count = n;
  if (box) *box = y_hi < 0 ? cv::Rect() : cv::Rect(x_lo, y_lo, x_hi - x_lo + 1, y_hi - y_lo + 1);
}

// a[i] = min(a[i], a[i + d]) for i in [0, n), in place (ascending, so a[i + d] is still the old
// value), 16 bytes at a time: reads a[0, n + d + 15).
void MinShiftedInPlace(uint8_t* a, int n, int d) {
  int i = 0;
#if CV_SIMD128
  for (; i < n; i += 16) cv::v_store(a + i, cv::v_min(cv::v_load(a + i), cv::v_load(a + i + d)));
#endif
  for (; i < n; ++i) a[i] = std::min(a[i], a[i + d]);
}

// out[i] = min(a[i], b[i]) for i in [0, n); out may be a, not b. When n >= 16 the last block
// overlaps the one before (harmless: b is unchanged), so nothing is left to a scalar tail.
void MinOf(const uint8_t* a, const uint8_t* b, int n, uint8_t* out) {
  int i = 0;
#if CV_SIMD128
  if (n >= 16) {
    for (;; i += 16) {
      if (i + 16 > n) i = n - 16;
      cv::v_store(out + i, cv::v_min(cv::v_load(a + i), cv::v_load(b + i)));
      if (i + 16 == n) break;
    }
    return;
  }
#endif
  for (; i < n; ++i) out[i] = std::min(a[i], b[i]);
}

// Binary erosion of a CV_8U mask (0 or 255) by a (2 r + 1) square, outside the image counting
// as unset: the minimum over 2 r + 1 columns, then over 2 r + 1 rows, each by doubling (minima
// over 1, 2, 4, .. P <= 2 r + 1 samples, then two overlapping P-windows: log steps instead of
// 2 r per pixel). Same result as cv::erode with a rectangle and BORDER_CONSTANT 0, without its
// per-call set-up.
void ErodeSquare(const cv::Mat& mask, int r, cv::Mat* tmp, cv::Mat* out,
                 std::vector<uint8_t>* padded) {
  const int w = mask.cols, h = mask.rows, e = 2 * r + 1;
  int p = 1;  // largest power of two <= e
  while (2 * p <= e) p *= 2;
  tmp->create(mask.size(), CV_8U);
  out->create(mask.size(), CV_8U);
  // Row: r zeros, the row, zeros; windows [x, x + e) of it are [x - r, x + r] of the row. Levels
  // are computed on [0, n), n past the last window's start, reading zeros beyond the row.
  const int n = (w + e + 15) / 16 * 16;
  padded->assign(n + 2 * e + 32, 0);
  uint8_t* pad = padded->data();
  for (int y = 0; y < h; ++y) {
    std::fill_n(pad, padded->size(), uint8_t{0});
    std::copy_n(mask.ptr<uint8_t>(y), w, pad + r);
    for (int d = 1; d < p; d *= 2) MinShiftedInPlace(pad, n, d);
    MinOf(pad, pad + e - p, w, tmp->ptr<uint8_t>(y));
  }
  // Columns: the same doubling over rows, in place in tmp (row i holds the minimum of rows
  // [i, i + d) after level d; only rows whose window lies inside are kept up to date).
  for (int d = 1; d < p; d *= 2) {
    for (int i = 0; i + 2 * d <= h; ++i) {
      MinOf(tmp->ptr<uint8_t>(i), tmp->ptr<uint8_t>(i + d), w, tmp->ptr<uint8_t>(i));
    }
  }
  for (int y = 0; y < h; ++y) {
    uint8_t* o = out->ptr<uint8_t>(y);
    if (y < r || y + r >= h) {
      std::fill_n(o, w, uint8_t{0});
      continue;
    }
    MinOf(tmp->ptr<uint8_t>(y - r), tmp->ptr<uint8_t>(y - r + e - p), w, o);
  }
}

// gx, gy = 3x3 Sobel of `src` on every step-th pixel of the rectangle r (both in one pass);
// reads outside r use src's real neighbours, clamped at src's edge.
void SobelXY(const cv::Mat& src, const cv::Rect& r, int step, cv::Mat* gx, cv::Mat* gy) {
  if (step > 1) {
    // The template of the fine level: a quarter of the samples, not worth a vector path.
    const cv::Size n((r.width + step - 1) / step, (r.height + step - 1) / step);
    gx->create(n, CV_32F);
    gy->create(n, CV_32F);
    for (int j = 0; j < n.height; ++j) {
      const int sy = r.y + step * j;
      const float* a = src.ptr<float>(std::max(0, sy - 1));
      const float* b = src.ptr<float>(sy);
      const float* c = src.ptr<float>(std::min(src.rows - 1, sy + 1));
      float* ox = gx->ptr<float>(j);
      float* oy = gy->ptr<float>(j);
      for (int i = 0; i < n.width; ++i) {
        const int x = r.x + step * i;
        const int l = std::max(x - 1, 0), rr = std::min(x + 1, src.cols - 1);
        ox[i] = (a[rr] - a[l]) + 2.0f * (b[rr] - b[l]) + (c[rr] - c[l]);
        oy[i] = (c[l] + 2.0f * c[x] + c[rr]) - (a[l] + 2.0f * a[x] + a[rr]);
      }
    }
    return;
  }
  gx->create(r.size(), CV_32F);
  gy->create(r.size(), CV_32F);
  const int x_lo = std::max(0, 1 - r.x), x_hi = std::min(r.width, src.cols - 1 - r.x);
  for (int y = 0; y < r.height; ++y) {
    const int sy = r.y + y;
    const float* a = src.ptr<float>(std::max(0, sy - 1)) + r.x;
    const float* b = src.ptr<float>(sy) + r.x;
    const float* c = src.ptr<float>(std::min(src.rows - 1, sy + 1)) + r.x;
    float* ox = gx->ptr<float>(y);
    float* oy = gy->ptr<float>(y);
    auto scalar = [&](int x) {
      const int l = std::max(x - 1, -r.x), rr = std::min(x + 1, src.cols - 1 - r.x);
      ox[x] = (a[rr] - a[l]) + 2.0f * (b[rr] - b[l]) + (c[rr] - c[l]);
      oy[x] = (c[l] + 2.0f * c[x] + c[rr]) - (a[l] + 2.0f * a[x] + a[rr]);
    };
    int x = 0;
    for (; x < x_lo; ++x) scalar(x);
#if CV_SIMD128
    const cv::v_float32x4 two = cv::v_setall_f32(2.0f);
    for (; x + 4 <= x_hi; x += 4) {
      const cv::v_float32x4 al = cv::v_load(a + x - 1), am = cv::v_load(a + x),
                            ar = cv::v_load(a + x + 1);
      const cv::v_float32x4 bl = cv::v_load(b + x - 1), br = cv::v_load(b + x + 1);
      const cv::v_float32x4 cl = cv::v_load(c + x - 1), cm = cv::v_load(c + x),
                            cr = cv::v_load(c + x + 1);
      cv::v_store(ox + x, (ar - al) + two * (br - bl) + (cr - cl));
      cv::v_store(oy + x, (cl + two * cm + cr) - (al + two * am + ar));
    }
#endif
    for (; x < r.width; ++x) scalar(x);
  }
}

// Sums over two fields' planes: num = sum tc bc + ts bs, den = sum td bd, over the template
// samples in_t, sample (x, y) of which meets base plane element b0 + step (x, y) (step 1 or 2).
// One pass, four lanes; rows summed in double.
void FieldSums(const cv::Mat& tc, const cv::Mat& ts, const cv::Mat& td, const cv::Mat& bc,
               const cv::Mat& bs, const cv::Mat& bd, const cv::Rect& in_t, cv::Point b0, int step,
               double* num, double* den) {
  double n = 0.0, d = 0.0;
  const int w = in_t.width;
  for (int y = 0; y < in_t.height; ++y) {
    const float* a_c = tc.ptr<float>(in_t.y + y) + in_t.x;
    const float* a_s = ts.ptr<float>(in_t.y + y) + in_t.x;
    const float* a_d = td.ptr<float>(in_t.y + y) + in_t.x;
    const float* b_c = bc.ptr<float>(b0.y + step * y) + b0.x;
    const float* b_s = bs.ptr<float>(b0.y + step * y) + b0.x;
    const float* b_d = bd.ptr<float>(b0.y + step * y) + b0.x;
    float row_n = 0.0f, row_d = 0.0f;
    int x = 0;
#if CV_SIMD128
    cv::v_float32x4 vn = cv::v_setzero_f32(), vd = cv::v_setzero_f32();
    if (step == 1) {
      for (; x + 4 <= w; x += 4) {
        vn += cv::v_load(a_c + x) * cv::v_load(b_c + x) + cv::v_load(a_s + x) * cv::v_load(b_s + x);
        vd += cv::v_load(a_d + x) * cv::v_load(b_d + x);
      }
    } else if (step == 2) {
      // De-interleaved loads read base elements 2x .. 2x + 7: stay inside the base row.
      const int fit = (bc.cols - b0.x) / 2 - 3;
      cv::v_float32x4 bce, bse, bde, odd;
      for (; x + 4 <= std::min(w, fit); x += 4) {
        cv::v_load_deinterleave(b_c + 2 * x, bce, odd);
        cv::v_load_deinterleave(b_s + 2 * x, bse, odd);
        cv::v_load_deinterleave(b_d + 2 * x, bde, odd);
        vn += cv::v_load(a_c + x) * bce + cv::v_load(a_s + x) * bse;
        vd += cv::v_load(a_d + x) * bde;
      }
    }
    row_n = cv::v_reduce_sum(vn);
    row_d = cv::v_reduce_sum(vd);
#endif
    for (; x < w; ++x) {
      const int bx = step * x;
      row_n += a_c[x] * b_c[bx] + a_s[x] * b_s[bx];
      row_d += a_d[x] * b_d[bx];
    }
    n += row_n;
    d += row_d;
  }
  *num = n;
  *den = d;
}

// Template samples first .. first + count - 1 of a field sampled at `step` from t_origin meet
// base plane elements b_first + step * (i - first) of a full-rate field of b_size elements from
// b_origin, at `offset` (one axis; count 0 when none does).
struct AxisOverlap {
  int first = 0, count = 0, b_first = 0;
};
AxisOverlap OverlapOnAxis(int t_origin, int t_samples, int step, int b_origin, int b_size,
                          int offset) {
  // Template sample i is base element d + step i.
  const int d = t_origin + offset - b_origin;
  auto floor_div = [step](int a) { return a >= 0 ? a / step : -((-a + step - 1) / step); };
  const int lo = std::max(0, -floor_div(d));  // ceil(-d / step)
  const int hi = std::min(t_samples - 1, floor_div(b_size - 1 - d));
  AxisOverlap o;
  if (hi < lo) return o;
  o.first = lo;
  o.count = hi - lo + 1;
  o.b_first = d + step * lo;
  return o;
}

// Sums rows y .. y + f - 1 of an integer image over columns 0 .. w - 1 into acc.
template <typename T>
void SumRows(const cv::Mat& image, int y, int f, int w, uint32_t* acc) {
  static_assert(std::is_same_v<T, uint8_t> || std::is_same_v<T, uint16_t>);
  for (int k = 0; k < f; ++k) {
    const T* in = image.ptr<T>(y + k);
    int x = 0;
#if CV_SIMD128
    for (; x + 4 <= w; x += 4) {
      cv::v_uint32x4 v;
      if constexpr (std::is_same_v<T, uint16_t>) {
        v = cv::v_load_expand(in + x);
      } else {
        v = LoadExpand4(in + x);
      }
      cv::v_store(acc + x, k == 0 ? v : cv::v_load(acc + x) + v);
    }
#endif
    for (; x < w; ++x) acc[x] = (k == 0 ? 0u : acc[x]) + in[x];
  }
}

// Sums rows y .. y + f - 1 of a float image over columns 0 .. w - 1 into acc.
void SumRows(const cv::Mat& image, int y, int f, int w, float* acc) {
  std::copy_n(image.ptr<float>(y), w, acc);
  for (int k = 1; k < f; ++k) {
    const float* in = image.ptr<float>(y + k);
    int x = 0;
#if CV_SIMD128
    for (; x + 4 <= w; x += 4) cv::v_store(acc + x, cv::v_load(acc + x) + cv::v_load(in + x));
#endif
    for (; x < w; ++x) acc[x] += in[x];
  }
}

// out[j] = scale * (acc[f j] + ... + acc[f j + f - 1]), j < n, summed as ((0 + 1) + (2 + 3))
// for f = 4 and left to right otherwise.
template <typename A>
void SumColumns(const A* acc, int f, int n, float scale, float* out) {
  int j = 0;
#if CV_SIMD128
  if (f == 4) {
    const cv::v_float32x4 s4 = cv::v_setall_f32(scale);
    for (; j + 4 <= n; j += 4) {
      if constexpr (std::is_same_v<A, float>) {
        cv::v_float32x4 p0, p1, p2, p3;
        cv::v_load_deinterleave(acc + 4 * j, p0, p1, p2, p3);
        cv::v_store(out + j, ((p0 + p1) + (p2 + p3)) * s4);
      } else {
        cv::v_uint32x4 p0, p1, p2, p3;
        cv::v_load_deinterleave(acc + 4 * j, p0, p1, p2, p3);
        const cv::v_uint32x4 sum = (p0 + p1) + (p2 + p3);
        cv::v_store(out + j, cv::v_cvt_f32(cv::v_reinterpret_as_s32(sum)) * s4);
      }
    }
  }
#endif
  for (; j < n; ++j) {
    A sum = acc[j * f];
    for (int k = 1; k < f; ++k) sum += acc[j * f + k];
    out[j] = static_cast<float>(sum) * scale;
  }
}

// Reduces image and mask by an integer factor (pixel i covers [f i, f i + f)); a reduced pixel
// is valid only when all its pixels are. Integer images are summed as integers (exact: at most
// 64 samples of 16 bits), floats as floats; either way the block mean is INTER_AREA's for an
// integer factor.
void Reduce(const cv::Mat& image, const cv::Mat& mask, int factor, cv::Mat* image_small,
            cv::Mat* mask_small, std::vector<float>* row_sum, std::vector<uint32_t>* row_isum,
            std::vector<uint8_t>* row_min) {
  const int f = factor;
  const cv::Size small(image.cols / f, image.rows / f);
  const int w = small.width * f;
  image_small->create(small, CV_32F);
  const float scale = 1.0f / static_cast<float>(f * f);
  const int depth = image.depth();
  if (depth == CV_32F) {
    row_sum->resize(w);
  } else {
    row_isum->resize(w);
  }
  for (int i = 0; i < small.height; ++i) {
    float* out = image_small->ptr<float>(i);
    if (depth == CV_8U) {
      SumRows<uint8_t>(image, i * f, f, w, row_isum->data());
      SumColumns(row_isum->data(), f, small.width, scale, out);
    } else if (depth == CV_16U) {
      SumRows<uint16_t>(image, i * f, f, w, row_isum->data());
      SumColumns(row_isum->data(), f, small.width, scale, out);
    } else {
      SumRows(image, i * f, f, w, row_sum->data());
      SumColumns(row_sum->data(), f, small.width, scale, out);
    }
  }
  if (mask.empty()) {
    mask_small->release();
    return;
  }
  // A reduced pixel is valid only when all its pixels are.
  mask_small->create(small, CV_8U);
  row_min->resize(w);
  uint8_t* mn = row_min->data();
  for (int i = 0; i < small.height; ++i) {
    std::copy_n(mask.ptr<uint8_t>(i * f), w, mn);
    for (int k = 1; k < f; ++k) {
      const uint8_t* in = mask.ptr<uint8_t>(i * f + k);
      int x = 0;
#if CV_SIMD128
      for (; x + 16 <= w; x += 16)
        cv::v_store(mn + x, cv::v_min(cv::v_load(mn + x), cv::v_load(in + x)));
#endif
      for (; x < w; ++x) mn[x] = std::min(mn[x], in[x]);
    }
    uint8_t* out = mask_small->ptr<uint8_t>(i);
    for (int j = 0; j < small.width; ++j) {
      bool all = true;
      for (int k = 0; k < f; ++k) all &= mn[j * f + k] != 0;
      out[j] = all ? 255 : 0;
    }
  }
}

}  // namespace

ScdMatcher::ScdMatcher(ScdOptions options) : options_(options) {
  if (!options_.IsValid(nullptr)) return;  // Match reports it.
  auto make = [](double sigma) {
    Filter f;
    std::vector<double> g{1.0};
    if (sigma > 0.0) {
      const int half = std::max(1, static_cast<int>(std::ceil(3.0 * sigma)));
      f.gauss = cv::getGaussianKernel(2 * half + 1, sigma, CV_32F);
      cv::Mat g64;
      f.gauss.convertTo(g64, CV_64F);
      g.assign(g64.begin<double>(), g64.end<double>());
    }
    // The separable Sobel-of-blur kernel is (g * [-1 0 1]) x (g * [1 2 1]).
    f.noise_gain = std::sqrt(SumOfSquares(Convolve(g, {-1.0, 0.0, 1.0})) *
                             SumOfSquares(Convolve(g, {1.0, 2.0, 1.0})));
    // A mask edge, whose step the mean fill keeps small, must not reach a kept gradient through
    // the blur (2 sigma holds 95 % of its weight) and the Sobel (1 px).
    f.erode_px = static_cast<int>(std::ceil(2.0 * sigma)) + 1;
    return f;
  };
  fine_ = make(options_.gradient_sigma_px);
  coarse_ = make(options_.coarse_gradient_sigma_px);
}

void ScdMatcher::ComputeField(const Filter& filter, const cv::Mat& image, const cv::Mat& mask,
                              const cv::Rect& roi, Scratch* scratch, Field* out,
                              double* noise_std_io, Field* unit, int step) {
  cv::Mat& work_f32 = scratch->work_f32;
  cv::Mat& work_mask = scratch->work_mask;
  cv::Mat& blurred = scratch->blurred;
  cv::Mat& gx_all = scratch->gx;
  cv::Mat& gy_all = scratch->gy;
  cv::Mat& tmp = scratch->tmp;
  const int margin = std::max(filter.erode_px, filter.gauss.rows / 2 + 2);
  const cv::Rect ext =
      cv::Rect(roi.x - margin, roi.y - margin, roi.width + 2 * margin, roi.height + 2 * margin) &
      cv::Rect(0, 0, image.cols, image.rows);
  const cv::Rect inner(roi.x - ext.x, roi.y - ext.y, roi.width, roi.height);
  // Float copy and validity (the mask, minus non-finite samples of float input), no-data filled
  // with the valid mean, in one fused pass (the seven OpenCV passes it replaces cost more).
  // Erosion below keeps only pixels that neither a mask edge nor the image border (where the
  // blur reflects the image) can reach through blur and Sobel. Outside the image counts as no
  // data; outside `ext` but inside the image is farther than the erosion reaches.
  LoadValidFilled(image(ext), mask.empty() ? cv::Mat() : mask(ext), &work_f32, &work_mask);
  ErodeSquare(work_mask, filter.erode_px, &tmp, &scratch->eroded, &erode_pad_);
  cv::swap(work_mask, scratch->eroded);
  double noise_std = *noise_std_io;
  if (noise_std < 0.0) {
    noise_std = options_.noise_floor_sigmas > 0.0 ? EstimateNoiseStd(work_f32, work_mask) : 0.0;
    *noise_std_io = noise_std;
  }
  if (filter.gauss.empty()) {
    work_f32.copyTo(blurred);
  } else {
    cv::sepFilter2D(work_f32, blurred, CV_32F, filter.gauss, filter.gauss, cv::Point(-1, -1), 0.0,
                    cv::BORDER_REFLECT);
  }
  SobelXY(blurred, inner, step, &gx_all, &gy_all);

  const float floor =
      static_cast<float>(options_.noise_floor_sigmas * noise_std * filter.noise_gain);
  out->region = roi;
  out->step = step;
  out->floor_sq = floor * floor;
  if (step == 1) {
    work_mask(inner).convertTo(out->valid, CV_32F, 1.0 / 255.0);
  } else {
    out->valid.create(gx_all.size(), CV_32F);
    for (int j = 0; j < gx_all.rows; ++j) {
      const uint8_t* m = work_mask.ptr<uint8_t>(inner.y + step * j) + inner.x;
      float* v = out->valid.ptr<float>(j);
      for (int i = 0; i < gx_all.cols; ++i) v[i] = m[step * i] ? 1.0f : 0.0f;
    }
  }
  const double valid_px = cv::countNonZero(out->valid);
  out->valid_px = valid_px;
  Normalise(gx_all, gy_all, options_.magnitude_weight_cap, out);
  if (unit) {
    unit->region = roi;
    unit->step = step;
    unit->floor_sq = out->floor_sq;
    unit->valid = out->valid;  // Shared: Normalise does not write it.
    unit->valid_px = valid_px;
    Normalise(gx_all, gy_all, 0.0, unit);
  }
}

void ScdMatcher::Normalise(const cv::Mat& gx_all, const cv::Mat& gy_all, double weight_cap,
                           Field* out) {
  const cv::Size size = gx_all.size();  // the field's planes (region sampled at its step)
  const float floor_sq = out->floor_sq;
  // Weighting w = min(cap, m / median) enters as inv = w / m = min(cap / m, 1 / median).
  const bool weighted = weight_cap > 0.0;
  float cap = 1.0f, inv_median = std::numeric_limits<float>::infinity();  // w = 1
  if (weighted) {
    // Median magnitude of the valid pixels, sampled on every fourth row and column of the
    // image (the same pixels at any step).
    magnitudes_.clear();
    const int every = std::max(1, 4 / out->step);
    for (int y = 0; y < size.height; y += every) {
      const float* gx = gx_all.ptr<float>(y);
      const float* gy = gy_all.ptr<float>(y);
      const float* v = out->valid.ptr<float>(y);
      for (int x = 0; x < size.width; x += every) {
        if (v[x] != 0.0f) magnitudes_.push_back(gx[x] * gx[x] + gy[x] * gy[x]);
      }
    }
    if (!magnitudes_.empty()) {
      auto mid = magnitudes_.begin() + static_cast<std::ptrdiff_t>(magnitudes_.size() / 2);
      std::nth_element(magnitudes_.begin(), mid, magnitudes_.end());
      if (*mid > 0.0f) {
        cap = static_cast<float>(weight_cap);
        inv_median = 1.0f / std::sqrt(*mid);
      }
    }
  }
  const bool mask_out_flat = options_.flat_handling == ScdFlatHandling::kMaskOut;
  const bool soft = options_.flat_handling == ScdFlatHandling::kSoft;
  out->cos_w.create(size, CV_32F);
  out->sin_w.create(size, CV_32F);
  if (mask_out_flat) {
    if (out->den_w.data == out->valid.data) out->den_w = cv::Mat();
    out->den_w.create(size, CV_32F);
  }
  double oriented_px = 0.0;
  for (int y = 0; y < size.height; ++y) {
    const float* gx = gx_all.ptr<float>(y);
    const float* gy = gy_all.ptr<float>(y);
    const float* v = out->valid.ptr<float>(y);
    float* c = out->cos_w.ptr<float>(y);
    float* s = out->sin_w.ptr<float>(y);
    float* d = mask_out_flat ? out->den_w.ptr<float>(y) : nullptr;
    int row_oriented = 0;
    int x = 0;
#if CV_SIMD128
    if (!soft && !mask_out_flat) {
      // Same arithmetic as the scalar loop below, four pixels at a time.
      const cv::v_float32x4 zero = cv::v_setzero_f32(), one = cv::v_setall_f32(1.0f);
      const cv::v_float32x4 floor4 = cv::v_setall_f32(floor_sq);
      const cv::v_float32x4 tiny = cv::v_setall_f32(1e-30f);
      const cv::v_float32x4 cap4 = cv::v_setall_f32(cap), inv_med4 = cv::v_setall_f32(inv_median);
      cv::v_float32x4 count = zero;
      for (; x + 4 <= size.width; x += 4) {
        const cv::v_float32x4 vx = cv::v_load(gx + x), vy = cv::v_load(gy + x);
        const cv::v_float32x4 m2 = vx * vx + vy * vy;
        const cv::v_float32x4 keep = (cv::v_load(v + x) != zero) & (m2 > floor4) & (m2 > zero);
        const cv::v_float32x4 inv_m = cv::v_invsqrt(cv::v_max(m2, tiny));
        const cv::v_float32x4 inv = cv::v_select(keep, cv::v_min(cap4 * inv_m, inv_med4), zero);
        cv::v_store(c + x, vx * inv);
        cv::v_store(s + x, vy * inv);
        count += cv::v_select(keep, one, zero);
      }
      row_oriented += static_cast<int>(cv::v_reduce_sum(count));
    }
#endif
    for (; x < size.width; ++x) {
      const bool is_valid = v[x] != 0.0f;
      const float mag_sq = gx[x] * gx[x] + gy[x] * gy[x];
      const bool oriented = is_valid && mag_sq > floor_sq && mag_sq > 0.0f;
      float inv = oriented ? std::min(cap / std::sqrt(mag_sq), inv_median) : 0.0f;
      if (soft && is_valid) {
        inv = std::sqrt(mag_sq) / (mag_sq + floor_sq + 1e-30f);
        if (weighted) inv *= std::min(cap, std::sqrt(mag_sq) * inv_median);
      }
      c[x] = gx[x] * inv;
      s[x] = gy[x] * inv;
      if (d) d[x] = oriented ? 1.0f : 0.0f;
      row_oriented += oriented;
    }
    oriented_px += row_oriented;
  }
  if (!mask_out_flat) out->den_w = out->valid;
  out->oriented_px = oriented_px;
}

void ScdMatcher::ForwardDft(const cv::Mat& src, int nonzero_rows, cv::Mat* spectrum) {
  // Plans depend on the geometry of the pair; bound the cache for long runs.
  if (dft_plans_.size() > 64) dft_plans_.clear();
  auto& plan = dft_plans_[{src.cols, src.rows, 0, nonzero_rows}];
  if (!plan) plan = cv::hal::DFT2D::create(src.cols, src.rows, CV_32F, 1, 1, 0, nonzero_rows);
  spectrum->create(src.size(), CV_32F);
  plan->apply(src.data, src.step, spectrum->data, spectrum->step);
}

void ScdMatcher::InverseDft(const cv::Mat& spectrum, int output_rows, cv::Mat* out) {
  const int flags = cv::DFT_INVERSE | cv::DFT_REAL_OUTPUT;
  auto& plan = dft_plans_[{spectrum.cols, spectrum.rows, flags, output_rows}];
  if (!plan) {
    plan = cv::hal::DFT2D::create(spectrum.cols, spectrum.rows, CV_32F, 1, 1, flags, output_rows);
  }
  out->create(spectrum.size(), CV_32F);
  plan->apply(spectrum.data, spectrum.step, out->data, out->step);
}

ScdResult::Status ScdMatcher::CheckFlat(const Field& f, const char* which,
                                        std::string* reason) const {
  if (f.valid_px == 0) {
    *reason = std::string("no valid ") + which + " pixel where the images can overlap";
    return Status::kTooLittleOverlap;
  }
  // Pure noise puts exp(-k^2/2) of the pixels over a floor of k sigmas (Rayleigh magnitude).
  const double k = options_.noise_floor_sigmas;
  const double noise_share = k >= 1.0 ? 1.5 * std::exp(-0.5 * k * k) : 0.0;
  const double min_oriented = options_.min_oriented_fraction + std::min(0.5, noise_share);
  if (f.oriented_px < std::max(1.0, min_oriented * f.valid_px)) {
    std::ostringstream s;
    s << which << " is flat: " << f.oriented_px << " of " << f.valid_px
      << " valid pixels have a gradient above the noise floor";
    *reason = s.str();
    return Status::kFlat;
  }
  return Status::kOk;
}

ScdResult::Status ScdMatcher::FftSearch(const Filter& filter, const cv::Mat& base,
                                        const cv::Mat& base_mask, const cv::Mat& templ,
                                        const cv::Mat& templ_mask, double templ_valid_px,
                                        cv::Point lo, cv::Point hi, Peak* peak,
                                        std::string* reason) {
  // Window clipped to offsets that put the template over the base.
  const int u0 = std::max(lo.x, 1 - templ.cols), u1 = std::min(hi.x, base.cols - 1);
  const int v0 = std::max(lo.y, 1 - templ.rows), v1 = std::min(hi.y, base.rows - 1);
  if (u0 > u1 || v0 > v1) {
    *reason = "no offset within the search radius puts the template over the base";
    return Status::kTooLittleOverlap;
  }
  const int nu = u1 - u0 + 1, nv = v1 - v0 + 1;
  // Template pixels that can meet the base for some offset; base pixels they can meet.
  const cv::Rect templ_roi(
      cv::Point(std::max(0, -u1), std::max(0, -v1)),
      cv::Point(std::min(templ.cols, base.cols - u0), std::min(templ.rows, base.rows - v0)));
  const cv::Rect base_roi(cv::Point(std::max(0, templ_roi.x + u0), std::max(0, templ_roi.y + v0)),
                          cv::Point(std::min(base.cols, templ_roi.br().x + u1),
                                    std::min(base.rows, templ_roi.br().y + v1)));
  Scratch& scratch = &filter == &fine_ ? fine_scratch_ : coarse_scratch_;
  Field& tfield = scratch.templ_field;
  Field& bfield = scratch.base_field;
  double templ_noise = -1.0, base_noise = -1.0;
  ComputeField(filter, templ, templ_mask, templ_roi, &scratch, &tfield, &templ_noise);
  ComputeField(filter, base, base_mask, base_roi, &scratch, &bfield, &base_noise);
  Status flat = CheckFlat(tfield, "template", reason);
  if (flat == Status::kOk) flat = CheckFlat(bfield, "base", reason);
  if (flat != Status::kOk) return flat;
  // Only the parts where valid template pixels can meet valid base pixels are transformed: the
  // masks' bounding boxes (the fields are zero elsewhere, so no correlation changes, and the FFT
  // gets smaller). The fields themselves are made on the whole parts as before (their noise
  // estimate and median depend on the region).
  const cv::Rect templ_valid =
      templ_mask.empty() ? cv::Rect(0, 0, templ.cols, templ.rows) : cv::boundingRect(templ_mask);
  const cv::Rect base_valid =
      base_mask.empty() ? cv::Rect(0, 0, base.cols, base.rows) : cv::boundingRect(base_mask);
  const cv::Rect templ_use = templ_roi & templ_valid &
                             cv::Rect(cv::Point(base_valid.x - u1, base_valid.y - v1),
                                      cv::Point(base_valid.br().x - u0, base_valid.br().y - v0));
  const cv::Rect base_use = base_roi & base_valid &
                            cv::Rect(cv::Point(templ_use.x + u0, templ_use.y + v0),
                                     cv::Point(templ_use.br().x + u1, templ_use.br().y + v1));
  if (templ_use.empty() || base_use.empty()) {
    *reason = "no valid template pixel can meet a valid base pixel within the search radius";
    return Status::kTooLittleOverlap;
  }

  // c(j) = sum_p t(p) b'(p + j), j = 0..n-1, with the base shifted right by d so that j = 0 is
  // offset (u0, v0); the FFT size leaves no wrap-around for those j.
  const int dx = base_use.x - (templ_use.x + u0), dy = base_use.y - (templ_use.y + v0);
  const int fft_w = FastDftSize(std::max({2, templ_use.width + nu - 1, dx + base_use.width}));
  const int fft_h = FastDftSize(std::max(templ_use.height + nv - 1, dy + base_use.height));
  const bool mask_out_flat = options_.flat_handling == ScdFlatHandling::kMaskOut;
  const int n_fields = mask_out_flat ? 4 : 3;
  // use: the part of the field transformed (image pixels), placed at `at` in the FFT array.
  auto transform = [&](const Field& f, const cv::Rect& use, cv::Point at, cv::Mat* spectra) {
    const cv::Mat* sources[4] = {&f.cos_w, &f.sin_w, &f.valid, &f.den_w};
    const cv::Rect in_field = use - f.region.tl(), place(at, use.size());
    pad_.create(fft_h, fft_w, CV_32F);
    pad_.setTo(0.0f);
    for (int k = 0; k < n_fields; ++k) {
      (*sources[k])(in_field).copyTo(pad_(place));  // Outside `place` stays zero.
      ForwardDft(pad_, place.br().y, &spectra[k]);
    }
  };
  transform(tfield, templ_use, cv::Point(0, 0), spec_t_);
  transform(bfield, base_use, cv::Point(dx, dy), spec_b_);
  cv::mulSpectrums(spec_b_[0], spec_t_[0], spec_num_, 0, true);
  cv::mulSpectrums(spec_b_[1], spec_t_[1], spec_den_, 0, true);
  spec_num_ += spec_den_;
  InverseDft(spec_num_, nv, &corr_num_);
  cv::mulSpectrums(spec_b_[2], spec_t_[2], spec_ovl_, 0, true);
  InverseDft(spec_ovl_, nv, &corr_ovl_);
  if (mask_out_flat) {
    cv::mulSpectrums(spec_b_[3], spec_t_[3], spec_den_, 0, true);
    InverseDft(spec_den_, nv, &corr_den_);
  }

  // Criterion inside the window; offsets with too little overlap get -inf (never NaN).
  const float inv_n = 1.0f / static_cast<float>(fft_w * fft_h);
  const float min_overlap =
      static_cast<float>(std::max(1.0, options_.min_overlap_fraction * templ_valid_px));
  const bool significance = options_.peak_criterion == ScdPeakCriterion::kSignificance;
  constexpr float kRejected = -std::numeric_limits<float>::infinity();
  score_.create(nv, nu, CV_32F);
  int best_x = -1, best_y = -1;
  float best = kRejected;
  for (int j = 0; j < nv; ++j) {
    const float* num = corr_num_.ptr<float>(j);
    const float* ovl = corr_ovl_.ptr<float>(j);
    const float* den = mask_out_flat ? corr_den_.ptr<float>(j) : ovl;
    float* out = score_.ptr<float>(j);
    for (int i = 0; i < nu; ++i) {
      float s = kRejected;
      if (ovl[i] * inv_n >= min_overlap && den[i] * inv_n >= 0.5f) {
        s = significance ? num[i] / std::sqrt(den[i] * inv_n) : num[i] / den[i];
      }
      out[i] = s;
      if (s > best) {
        best = s;
        best_x = i;
        best_y = j;
      }
    }
  }
  if (best_x < 0) {
    std::ostringstream s;
    s << "no offset in the search window overlaps at least " << options_.min_overlap_fraction
      << " of the template's " << templ_valid_px << " valid pixels";
    *reason = s.str();
    return Status::kTooLittleOverlap;
  }

  // Best local maximum outside the peak's neighbourhood.
  const double excl_sq = options_.peak_exclusion_px * options_.peak_exclusion_px;
  float second = kRejected;
  for (int j = 0; j < nv; ++j) {
    for (int i = 0; i < nu; ++i) {
      const float s = score_.at<float>(j, i);
      if (s <= second || s == kRejected) continue;
      const double ddx = i - best_x, ddy = j - best_y;
      if (ddx * ddx + ddy * ddy <= excl_sq) continue;
      bool is_max = true;
      for (int b = std::max(0, j - 1); b <= std::min(nv - 1, j + 1) && is_max; ++b) {
        for (int a = std::max(0, i - 1); a <= std::min(nu - 1, i + 1); ++a) {
          if (score_.at<float>(b, a) > s) {
            is_max = false;
            break;
          }
        }
      }
      if (is_max) second = s;
    }
  }
  auto at = [&](int i, int j) { return static_cast<double>(score_.at<float>(j, i)); };
  peak->offset = cv::Point(u0 + best_x, v0 + best_y);
  peak->subpixel.setZero();
  if (best_x > 0 && best_x + 1 < nu && at(best_x - 1, best_y) > kRejected &&
      at(best_x + 1, best_y) > kRejected) {
    peak->subpixel.x() =
        RefineAxis(options_.subpixel, at(best_x - 1, best_y), best, at(best_x + 1, best_y));
  }
  if (best_y > 0 && best_y + 1 < nv && at(best_x, best_y - 1) > kRejected &&
      at(best_x, best_y + 1) > kRejected) {
    peak->subpixel.y() =
        RefineAxis(options_.subpixel, at(best_x, best_y - 1), best, at(best_x, best_y + 1));
  }
  constexpr double kMaxRatio = 1e3;  // Reported when no other peak scores above zero.
  peak->ratio = !(best > 0.0f)  ? 0.0
                : second > 0.0f ? std::min(kMaxRatio, best / static_cast<double>(second))
                                : kMaxRatio;
  return Status::kOk;
}

bool ScdMatcher::Evaluate(const Field& tfield, const Field& bfield, cv::Point offset,
                          double* criterion, double* scd) const {
  // Template samples over the base field, and the base element of the first.
  const AxisOverlap ox = OverlapOnAxis(tfield.region.x, tfield.cos_w.cols, tfield.step,
                                       bfield.region.x, bfield.cos_w.cols, offset.x);
  const AxisOverlap oy = OverlapOnAxis(tfield.region.y, tfield.cos_w.rows, tfield.step,
                                       bfield.region.y, bfield.cos_w.rows, offset.y);
  if (ox.count == 0 || oy.count == 0) return false;
  double num = 0.0, den = 0.0;
  FieldSums(tfield.cos_w, tfield.sin_w, tfield.den_w, bfield.cos_w, bfield.sin_w, bfield.den_w,
            cv::Rect(ox.first, oy.first, ox.count, oy.count), cv::Point(ox.b_first, oy.b_first),
            tfield.step, &num, &den);
  if (!(den >= 0.5)) return false;
  *scd = std::clamp(num / den, -1.0, 1.0);
  *criterion =
      options_.peak_criterion == ScdPeakCriterion::kSignificance ? num / std::sqrt(den) : num / den;
  return true;
}

double ScdMatcher::EvaluateShifted(cv::Point offset, const Eigen::Vector2d& shift, double* scd) {
  constexpr double kNone = -std::numeric_limits<double>::infinity();
  if (!(shift.cwiseAbs().maxCoeff() < 2.0)) return kNone;
  const Field& base = fine_scratch_.base_field;
  const Field& templ =
      options_.magnitude_weight_cap > 0.0 ? fine_scratch_.templ_unit : fine_scratch_.templ_field;
  const int step = templ.step;
  const AxisOverlap ox = OverlapOnAxis(templ.region.x, templ.cos_w.cols, step, base.region.x,
                                       base.valid.cols, offset.x);
  const AxisOverlap oy = OverlapOnAxis(templ.region.y, templ.cos_w.rows, step, base.region.y,
                                       base.valid.rows, offset.y);
  if (ox.count == 0 || oy.count == 0) return kNone;
  const cv::Rect in_t(ox.first, oy.first, ox.count, oy.count);
  const cv::Point b0(ox.b_first, oy.b_first);
  // shifted(k) = gradient(b0 + step k + shift) at the template's samples only (gx, gy cover
  // base.region); reads past the gradients' edge are clamped, and reach at most 2 px in, where
  // Refine's margin keeps the overlap out.
  // The vertical passes are kept for the next call with the same shift.y (the refit's centre
  // and x neighbours share one).
  ShiftRows& rows = shift_rows_;
  if (!(rows.valid && rows.origin == b0 && rows.count == in_t.size() && rows.step == step &&
        rows.shift_y == shift.y())) {
    CubicRows(fine_scratch_.gx, b0, in_t.size(), step, shift.y(), &rows.gx);
    CubicRows(fine_scratch_.gy, b0, in_t.size(), step, shift.y(), &rows.gy);
    rows.valid = true;
    rows.origin = b0;
    rows.count = in_t.size();
    rows.step = step;
    rows.shift_y = shift.y();
  }
  CubicColumns(rows.gx, in_t.size(), step, shift.x(), &shifted_gx_);
  CubicColumns(rows.gy, in_t.size(), step, shift.x(), &shifted_gy_);
  // Unit vectors of the shifted gradients (Normalise without weighting) dotted with the
  // template's on the fly: num = sum t . b / |b| over oriented base pixels.
  const float floor_sq = base.floor_sq;
  const bool mask_out_flat = options_.flat_handling == ScdFlatHandling::kMaskOut;
  const bool soft = options_.flat_handling == ScdFlatHandling::kSoft;
  // De-interleaved loads of the base validity (step 2) read elements 2x .. 2x + 7.
  const int simd_width =
      step == 1 ? in_t.width : std::min(in_t.width, (base.valid.cols - b0.x) / 2 - 3);
  double num = 0.0, den = 0.0;
  for (int y = 0; y < in_t.height; ++y) {
    const float* tc = templ.cos_w.ptr<float>(in_t.y + y) + in_t.x;
    const float* ts = templ.sin_w.ptr<float>(in_t.y + y) + in_t.x;
    const float* td = templ.den_w.ptr<float>(in_t.y + y) + in_t.x;
    const float* v = base.valid.ptr<float>(b0.y + step * y) + b0.x;
    const float* gx = shifted_gx_.ptr<float>(y);
    const float* gy = shifted_gy_.ptr<float>(y);
    float row_n = 0.0f, row_d = 0.0f;
    int x = 0;
#if CV_SIMD128
    if (!soft && step <= 2) {
      const cv::v_float32x4 zero = cv::v_setzero_f32(), one = cv::v_setall_f32(1.0f);
      const cv::v_float32x4 floor4 = cv::v_setall_f32(floor_sq);
      const cv::v_float32x4 tiny = cv::v_setall_f32(1e-30f);
      cv::v_float32x4 vn = zero, vd = zero, valid, odd;
      for (; x + 4 <= simd_width; x += 4) {
        const cv::v_float32x4 bx = cv::v_load(gx + x), by = cv::v_load(gy + x);
        if (step == 1) {
          valid = cv::v_load(v + x);
        } else {
          cv::v_load_deinterleave(v + 2 * x, valid, odd);
        }
        const cv::v_float32x4 m2 = bx * bx + by * by;
        const cv::v_float32x4 keep = (valid != zero) & (m2 > floor4) & (m2 > zero);
        const cv::v_float32x4 inv = cv::v_select(keep, cv::v_invsqrt(cv::v_max(m2, tiny)), zero);
        vn += (cv::v_load(tc + x) * bx + cv::v_load(ts + x) * by) * inv;
        vd += cv::v_load(td + x) * (mask_out_flat ? cv::v_select(keep, one, zero) : valid);
      }
      row_n = cv::v_reduce_sum(vn);
      row_d = cv::v_reduce_sum(vd);
    }
#endif
    for (; x < in_t.width; ++x) {
      const float bx = gx[x], by = gy[x];
      const float vx = v[step * x];
      const bool is_valid = vx != 0.0f;
      const float m2 = bx * bx + by * by;
      const bool oriented = is_valid && m2 > floor_sq && m2 > 0.0f;
      float inv = oriented ? 1.0f / std::sqrt(m2) : 0.0f;
      if (soft && is_valid) inv = std::sqrt(m2) / (m2 + floor_sq + 1e-30f);
      row_n += (tc[x] * bx + ts[x] * by) * inv;
      row_d += td[x] * (mask_out_flat ? (oriented ? 1.0f : 0.0f) : vx);
    }
    num += row_n;
    den += row_d;
  }
  if (!(den >= 0.5)) return kNone;
  if (scd) *scd = std::clamp(num / den, -1.0, 1.0);
  return options_.peak_criterion == ScdPeakCriterion::kSignificance ? num / std::sqrt(den)
                                                                    : num / den;
}

ScdResult::Status ScdMatcher::Refine(const cv::Mat& base, const cv::Mat& base_mask,
                                     const cv::Mat& templ, const cv::Mat& templ_mask,
                                     cv::Point start, cv::Point lo, cv::Point hi, int max_steps,
                                     Peak* peak, std::string* reason) {
  // Fine fields over the overlap at `start`, grown by how far the climb may go.
  const int grow = max_steps + 1;
  const cv::Rect templ_rect(0, 0, templ.cols, templ.rows), base_rect(0, 0, base.cols, base.rows);
  cv::Rect t_roi = templ_rect & (base_rect - start);
  if (!t_roi.empty() && (!templ_mask.empty() || !base_mask.empty())) {
    // Only the bounding box of the valid overlap: with irregular masks it is much smaller.
    const cv::Mat t = templ_mask.empty() ? base_mask(t_roi + start) : templ_mask(t_roi);
    const cv::Mat b = base_mask.empty() ? t : base_mask(t_roi + start);
    int64_t both = 0;
    cv::Rect box;
    BothSet(t, b, &both, &box);
    t_roi = box + t_roi.tl();
  }
  t_roi =
      cv::Rect(t_roi.x - grow, t_roi.y - grow, t_roi.width + 2 * grow, t_roi.height + 2 * grow) &
      templ_rect;
  cv::Rect b_roi = t_roi + start;
  b_roi =
      cv::Rect(b_roi.x - grow, b_roi.y - grow, b_roi.width + 2 * grow, b_roi.height + 2 * grow) &
      base_rect;
  if (t_roi.empty() || b_roi.empty()) {
    *reason = "the coarse peak leaves no overlap at full resolution";
    return Status::kTooLittleOverlap;
  }
  double templ_noise = -1.0, base_noise = -1.0;
  const bool weighted = options_.magnitude_weight_cap > 0.0;
  ComputeField(fine_, templ, templ_mask, t_roi, &fine_scratch_, &fine_scratch_.templ_field,
               &templ_noise, weighted ? &fine_scratch_.templ_unit : nullptr,
               options_.fine_template_step);
  ComputeField(fine_, base, base_mask, b_roi, &fine_scratch_, &fine_scratch_.base_field,
               &base_noise);
  shift_rows_.valid = false;  // New gradients: no vertical pass of EvaluateShifted holds.

  // Memoised criterion on a small grid around start.
  const int half = max_steps + 1, side = 2 * half + 1;
  constexpr double kUnset = std::numeric_limits<double>::quiet_NaN();
  constexpr double kNone = -std::numeric_limits<double>::infinity();
  std::array<double, 21 * 21> grid;
  std::array<double, 21 * 21> scd_grid;
  grid.fill(kUnset);
  auto value = [&](cv::Point o) {
    const int gi = (o.y - start.y + half) * side + (o.x - start.x + half);
    if (o.x < lo.x || o.x > hi.x || o.y < lo.y || o.y > hi.y || std::abs(o.x - start.x) > half ||
        std::abs(o.y - start.y) > half) {
      return kNone;
    }
    if (std::isnan(grid[gi])) {
      double c = kNone, s = 0.0;
      if (!Evaluate(fine_scratch_.templ_field, fine_scratch_.base_field, o, &c, &s)) c = kNone;
      grid[gi] = c;
      scd_grid[gi] = s;
    }
    return grid[gi];
  };
  cv::Point at = start;
  for (int step = 0; step <= max_steps; ++step) {
    cv::Point next = at;
    double best = value(at);
    for (int dy = -1; dy <= 1; ++dy) {
      for (int dx = -1; dx <= 1; ++dx) {
        const cv::Point o = at + cv::Point(dx, dy);
        if (std::abs(o.x - start.x) >= half || std::abs(o.y - start.y) >= half) continue;
        const double v = value(o);
        if (v > best) {
          best = v;
          next = o;
        }
      }
    }
    if (next == at) break;
    at = next;
  }
  const double c = value(at);
  if (c == kNone) {
    *reason = "no overlap at full resolution around the coarse peak";
    return Status::kTooLittleOverlap;
  }
  peak->offset = at;
  peak->subpixel.setZero();
  const double l = value(at - cv::Point(1, 0)), r = value(at + cv::Point(1, 0));
  const double u = value(at - cv::Point(0, 1)), d = value(at + cv::Point(0, 1));
  if (l > kNone && r > kNone) peak->subpixel.x() = RefineAxis(options_.subpixel, l, c, r);
  if (u > kNone && d > kNone) peak->subpixel.y() = RefineAxis(options_.subpixel, u, c, d);
  peak->ratio = scd_grid[(at.y - start.y + half) * side + (at.x - start.x + half)];  // SCD
  if (weighted) {
    // The reported score is the paper's (unweighted) SCD: unit vectors of the base gradients
    // made on the fly (a zero shift resamples nothing), no unit field of the base kept.
    double scd = 0.0;
    if (EvaluateShifted(at, Eigen::Vector2d::Zero(), &scd) > kNone) peak->ratio = scd;
  }
  const double h = options_.subpixel_step_px;
  if (h > 0.0) {
    // Second fit at +-h around the first estimate, all on resampled gradients (same smoothing).
    const Eigen::Vector2d s0 = peak->subpixel;
    const double c0 = EvaluateShifted(at, s0);
    const double xl = EvaluateShifted(at, s0 - Eigen::Vector2d(h, 0));
    const double xr = EvaluateShifted(at, s0 + Eigen::Vector2d(h, 0));
    const double yl = EvaluateShifted(at, s0 - Eigen::Vector2d(0, h));
    const double yr = EvaluateShifted(at, s0 + Eigen::Vector2d(0, h));
    // Vertex within +-subpixel_refit_max_px of the first estimate (see ScdOptions).
    const double max_move = options_.subpixel_refit_max_px;
    auto vertex = [h, max_move](double lower, double mid, double upper) {
      const double curvature = lower - 2.0 * mid + upper;
      return curvature < 0.0
                 ? std::clamp(0.5 * h * (lower - upper) / curvature, -max_move, max_move)
                 : 0.0;
    };
    if (c0 > kNone && xl > kNone && xr > kNone) peak->subpixel.x() = s0.x() + vertex(xl, c0, xr);
    if (c0 > kNone && yl > kNone && yr > kNone) peak->subpixel.y() = s0.y() + vertex(yl, c0, yr);
  }
  return Status::kOk;
}

ScdResult ScdMatcher::Match(const cv::Mat& base, const cv::Mat& base_mask, const cv::Mat& templ,
                            const cv::Mat& templ_mask, const Eigen::Vector2d& predicted_offset,
                            double search_radius_px) {
  ScdResult result;
  auto fail = [&result](Status status, const std::string& reason) {
    result.status = status;
    result.reason = reason;
    return result;
  };
  std::string error;
  if (!options_.IsValid(&error)) return fail(Status::kBadInput, "invalid ScdOptions: " + error);
  if (base.empty() || templ.empty()) {
    return fail(Status::kBadInput, base.empty() ? "base image is empty" : "template is empty");
  }
  if (!IsSupportedImage(base) || !IsSupportedImage(templ)) {
    return fail(Status::kBadInput, "images must be one channel CV_8U, CV_16U or CV_32F (base " +
                                       Describe(base) + ", template " + Describe(templ) + ")");
  }
  if (!IsSupportedMask(base_mask, base) || !IsSupportedMask(templ_mask, templ)) {
    return fail(Status::kBadInput,
                "masks must be empty or CV_8U one channel of their image's size (base mask " +
                    Describe(base_mask) + ", template mask " + Describe(templ_mask) + ")");
  }
  if (!predicted_offset.allFinite()) {
    return fail(Status::kBadInput, "predicted offset is not finite");
  }
  if (!std::isfinite(search_radius_px) || search_radius_px < 0.0 ||
      search_radius_px > options_.max_search_radius_px) {
    return fail(Status::kBadInput, "search radius must be in [0, max_search_radius_px]");
  }
  const double templ_valid_px =
      templ_mask.empty() ? static_cast<double>(templ.total()) : cv::countNonZero(templ_mask);
  if (templ_valid_px == 0) return fail(Status::kBadInput, "template mask has no valid pixel");
  if (!base_mask.empty() && cv::countNonZero(base_mask) == 0) {
    return fail(Status::kBadInput, "base mask has no valid pixel");
  }

  // Integer offsets of the (Chebyshev) search window that put the template over the base.
  const double lo_x =
      std::max(std::ceil(predicted_offset.x() - search_radius_px), 1.0 - templ.cols);
  const double hi_x =
      std::min(std::floor(predicted_offset.x() + search_radius_px), base.cols - 1.0);
  const double lo_y =
      std::max(std::ceil(predicted_offset.y() - search_radius_px), 1.0 - templ.rows);
  const double hi_y =
      std::min(std::floor(predicted_offset.y() + search_radius_px), base.rows - 1.0);
  if (lo_x > hi_x || lo_y > hi_y) {
    return fail(Status::kTooLittleOverlap,
                "no offset within the search radius puts the template over the base");
  }
  const cv::Point lo(static_cast<int>(lo_x), static_cast<int>(lo_y));
  const cv::Point hi(static_cast<int>(hi_x), static_cast<int>(hi_y));

  // Coarse search by FFT (at full resolution when the factor is 1 or the images are small).
  int f = options_.pyramid_factor;
  while (f > 1 &&
         (std::min(templ.cols, templ.rows) / f < 16 || std::min(base.cols, base.rows) / f < 16)) {
    f /= 2;
  }
  Peak peak;
  Status status;
  if (f == 1) {
    status =
        FftSearch(fine_, base, base_mask, templ, templ_mask, templ_valid_px, lo, hi, &peak, &error);
  } else {
    // Reduce only what the window can use (plus context for the coarse blur and erosion),
    // from corners on multiples of f so that reduced pixels tile the full ones exactly.
    const cv::Rect t_need(
        cv::Point(std::max(0, -hi.x), std::max(0, -hi.y)),
        cv::Point(std::min(templ.cols, base.cols - lo.x), std::min(templ.rows, base.rows - lo.y)));
    const cv::Rect b_need(cv::Point(std::max(0, t_need.x + lo.x), std::max(0, t_need.y + lo.y)),
                          cv::Point(std::min(base.cols, t_need.br().x + hi.x),
                                    std::min(base.rows, t_need.br().y + hi.y)));
    const int pad = f * (std::max(coarse_.erode_px, coarse_.gauss.rows / 2 + 2) + 2);
    auto crop = [f, pad](const cv::Rect& need, const cv::Mat& image) {
      const int x0 = std::max(0, need.x - pad) / f * f, y0 = std::max(0, need.y - pad) / f * f;
      const int x1 = std::min(image.cols, need.br().x + pad);
      const int y1 = std::min(image.rows, need.br().y + pad);
      return cv::Rect(cv::Point(x0, y0), cv::Point(x1, y1));
    };
    const cv::Rect t_crop = crop(t_need, templ), b_crop = crop(b_need, base);
    if (t_crop.width < f || t_crop.height < f || b_crop.width < f || b_crop.height < f) {
      return fail(Status::kTooLittleOverlap, "the images overlap by less than a reduced pixel");
    }
    Reduce(base(b_crop), base_mask.empty() ? cv::Mat() : base_mask(b_crop), f, &base_small_,
           &base_mask_small_, &reduce_sum_, &reduce_isum_, &erode_pad_);
    Reduce(templ(t_crop), templ_mask.empty() ? cv::Mat() : templ_mask(t_crop), f, &templ_small_,
           &templ_mask_small_, &reduce_sum_, &reduce_isum_, &erode_pad_);
    // Template crop pixel i <-> template f i + T0, base crop j <-> base f j + B0, so the full
    // offset is u = f (j - i) + (B0 - T0); the coarse window covers the fine one.
    const cv::Point shift = b_crop.tl() - t_crop.tl();
    auto floor_div = [f](int a) { return a >= 0 ? a / f : -((-a + f - 1) / f); };
    const cv::Point lo_small(floor_div(lo.x - shift.x), floor_div(lo.y - shift.y));
    const cv::Point hi_small(floor_div(hi.x - shift.x + f - 1), floor_div(hi.y - shift.y + f - 1));
    status = FftSearch(coarse_, base_small_, base_mask_small_, templ_small_, templ_mask_small_,
                       std::max(1.0, templ_valid_px / (f * f)), lo_small, hi_small, &peak, &error);
    peak.offset = peak.offset * f + shift;
    peak.subpixel *= f;
  }
  if (status != Status::kOk) return fail(status, error);
  const double ratio = peak.ratio;
  if (f > 1 && options_.refine_at_full_resolution) {
    const Eigen::Vector2d coarse = Eigen::Vector2d(peak.offset.x, peak.offset.y) + peak.subpixel;
    const cv::Point start(std::clamp(static_cast<int>(std::lround(coarse.x())), lo.x, hi.x),
                          std::clamp(static_cast<int>(std::lround(coarse.y())), lo.y, hi.y));
    status = Refine(base, base_mask, templ, templ_mask, start, lo, hi, std::min(f + 1, 9), &peak,
                    &error);
    if (status != Status::kOk) return fail(status, error);
    result.score = peak.ratio;  // Refine leaves the SCD at the peak there.
  }
  result.offset = Eigen::Vector2d(peak.offset.x, peak.offset.y) + peak.subpixel;
  result.peak_ratio = ratio;
  if (f == 1) {
    const int i = peak.offset.x - std::max(lo.x, 1 - templ.cols);
    const int j = peak.offset.y - std::max(lo.y, 1 - templ.rows);
    const bool mask_out_flat = options_.flat_handling == ScdFlatHandling::kMaskOut;
    const double num = corr_num_.at<float>(j, i);
    const double den = (mask_out_flat ? corr_den_ : corr_ovl_).at<float>(j, i);
    result.score = den > 0 ? std::clamp(num / den, -1.0, 1.0) : 0.0;
  }

  // Overlap at the integer peak, counted on the masks as given (not eroded).
  const int peak_u = peak.offset.x, peak_v = peak.offset.y;
  const cv::Rect in_templ =
      cv::Rect(0, 0, templ.cols, templ.rows) & cv::Rect(-peak_u, -peak_v, base.cols, base.rows);
  const cv::Rect in_base = in_templ + cv::Point(peak_u, peak_v);
  if (templ_mask.empty() && base_mask.empty()) {
    result.overlap_px = in_templ.area();
  } else if (templ_mask.empty()) {
    result.overlap_px = cv::countNonZero(base_mask(in_base));
  } else if (base_mask.empty()) {
    result.overlap_px = cv::countNonZero(templ_mask(in_templ));
  } else {
    int64_t both = 0;
    BothSet(templ_mask(in_templ), base_mask(in_base), &both, nullptr);
    result.overlap_px = static_cast<double>(both);
  }
  result.overlap_fraction = result.overlap_px / templ_valid_px;

  if (!(ratio > 0.0)) return fail(Status::kAmbiguous, "no offset has a positive SCD score");
  if (ratio < options_.min_peak_ratio) {
    std::ostringstream s;
    s << "peak ratio " << ratio << " is under " << options_.min_peak_ratio << " (SCD score "
      << result.score << ")";
    return fail(Status::kAmbiguous, s.str());
  }
  result.status = Status::kOk;
  return result;
}

}  // namespace irmosaic
