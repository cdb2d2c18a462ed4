#pragma once

// Where a square fits inside a mask: a square erosion of a binary mask, over a region of it.
// Header-only (internal), so its test can compare it with cv::erode.
//
// The masks registration sees are orthoimage footprints of frames: the image of a rectangle
// under a homography, convex, so each row holds one run of set pixels. For such masks the
// erosion is a run per row: the row's run shrunk by the square's half-size, intersected over
// the square's rows. That costs a scan of each row (8 bytes at a time) and a few operations per
// row, against cv::erode's pass of the whole square's width over every pixel twice, which at
// the pipeline's half-sizes (about 30 px) was 6-9 % of a pair registration's CPU. A row with
// more than one run sends the whole region to cv::erode; the two give identical results.

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

namespace irmosaic {
namespace erosion_detail {

inline uint64_t Load8(const unsigned char* p) {
  uint64_t w;
  std::memcpy(&w, p, sizeof w);
  return w;
}

// True when one of the 8 bytes of `w` is zero.
inline bool HasZeroByte(uint64_t w) {
  return ((w - 0x0101010101010101ULL) & ~w & 0x8080808080808080ULL) != 0;
}

// The run [*begin, *end) of non-zero bytes of row[0, n); false when the row holds more than one
// run. A row without any gives an empty run.
inline bool SingleRun(const unsigned char* row, int n, int* begin, int* end) {
  int x = 0;
  while (x + 8 <= n && Load8(row + x) == 0) x += 8;
  while (x < n && row[x] == 0) ++x;
  *begin = x;
  while (x + 8 <= n && !HasZeroByte(Load8(row + x))) x += 8;
  while (x < n && row[x] != 0) ++x;
  *end = x;
  while (x + 8 <= n && Load8(row + x) == 0) x += 8;
  while (x < n && row[x] == 0) ++x;
  return x == n;
}

}  // namespace erosion_detail

// For each pixel of `region`: 255 when the square of half-size `half` around it lies entirely
// where `mask` (CV_8U) is non-zero, else 0 (all 255 for an empty mask). `region` grown by `half`
// on every side must lie inside the mask.
inline cv::Mat SquaresInsideMask(const cv::Mat& mask, const cv::Rect& region, int half) {
  if (mask.empty()) return cv::Mat(region.size(), CV_8U, cv::Scalar(255));
  const cv::Rect outer(region.x - half, region.y - half, region.width + 2 * half,
                       region.height + 2 * half);
  const cv::Mat m = mask(outer);
  const int side = 2 * half + 1;
  // Each outer row's run shrunk by `half` on both sides: the x (outer pixels) whose horizontal
  // segment of the square is inside. Empty as [0, 0).
  std::vector<int> lo(outer.height), hi(outer.height);
  bool runs = true;
  for (int y = 0; y < outer.height && runs; ++y) {
    int b = 0, e = 0;
    runs = erosion_detail::SingleRun(m.ptr<unsigned char>(y), outer.width, &b, &e);
    if (e - b >= side) {
      lo[y] = b + half;
      hi[y] = e - half;
    } else {
      lo[y] = hi[y] = 0;
    }
  }
  if (!runs) {
    cv::Mat binary, eroded;
    cv::compare(m, 0, binary, cv::CMP_NE);
    cv::erode(binary, eroded, cv::getStructuringElement(cv::MORPH_RECT, cv::Size(side, side)));
    return eroded(cv::Rect(half, half, region.width, region.height));
  }
  cv::Mat out(region.size(), CV_8U);
  // Region row y is outer row y + half; its square spans outer rows y .. y + 2 half: the
  // largest lo and the smallest hi over those rows, by monotonic queues of row indices (one
  // pass, where a scan of the square's rows per row cost 2 half + 1 steps each).
  std::vector<int> most_lo(outer.height), least_hi(outer.height);
  int lo_head = 0, lo_tail = 0, hi_head = 0, hi_tail = 0;
  for (int k = 0; k < outer.height; ++k) {
    while (lo_tail > lo_head && lo[most_lo[lo_tail - 1]] <= lo[k]) --lo_tail;
    most_lo[lo_tail++] = k;
    while (hi_tail > hi_head && hi[least_hi[hi_tail - 1]] >= hi[k]) --hi_tail;
    least_hi[hi_tail++] = k;
    const int y = k - 2 * half;  // The region row whose square ends at outer row k.
    if (y < 0) continue;
    while (most_lo[lo_head] < y) ++lo_head;
    while (least_hi[hi_head] < y) ++hi_head;
    int a = std::max(0, lo[most_lo[lo_head]]);
    int b = std::min(outer.width, hi[least_hi[hi_head]]);
    // Outer x in [a, b) is region x in [a - half, b - half).
    a = std::clamp(a - half, 0, region.width);
    b = std::clamp(b - half, a, region.width);
    unsigned char* row = out.ptr<unsigned char>(y);
    std::memset(row, 0, a);
    std::memset(row + a, 255, b - a);
    std::memset(row + b, 0, region.width - b);
  }
  return out;
}

}  // namespace irmosaic
