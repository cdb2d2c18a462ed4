#pragma once
// Private helper (src/orthorectify.cc, src/map_fusion.cc): images of varying size carved out
// of one buffer that only grows, so a renderer allocates nothing per frame once it has seen
// its largest size (cv::Mat::create reallocates on any size change, and per-frame buffers of
// varying size fragment the heap of a long flight: docs/benchmarks.md, "Session 7"). Not
// installed.
#include <opencv2/core.hpp>

namespace irmosaic {

// A continuous `size` x `type` image over `*backing`, grown (by a quarter more than needed)
// when too small. Valid until the next call with the same backing; the caller owns no data.
inline cv::Mat BufferView(cv::Mat* backing, cv::Size size, int type) {
  const size_t bytes = static_cast<size_t>(size.area()) * CV_ELEM_SIZE(type);
  if (backing->empty() || backing->total() * backing->elemSize() < bytes) {
    backing->create(1, static_cast<int>(bytes + bytes / 4 + 64), CV_8U);
  }
  return cv::Mat(size, type, backing->data);
}

}  // namespace irmosaic
