#pragma once
// Private helper (src/mosaicker.cc, src/tile_store.cc): fixed-size image buffers that live
// long and come and go all flight (held frame images, tile images) taken from a pool that
// keeps them instead of returning them to the heap. Allocated and freed one by one, such
// buffers sit among the short-lived buffers of every frame and leave holes the heap keeps
// as free memory (docs/benchmarks.md, "Session 12"). Not installed.
#include <cstddef>
#include <mutex>
#include <opencv2/core.hpp>
#include <vector>

namespace irmosaic {

// A pool of buffers of one size and type. Take() hands out a buffer no one else references;
// the caller's cv::Mat (and its copies) hold it, and it returns to the pool when the last of
// them is released (the pool keeps one reference: a buffer is free when that is the only
// one). At most `capacity` buffers are pooled; past that Take() allocates ordinary ones.
// Thread-safe.
class MatPool {
 public:
  MatPool(int rows, int cols, int type, size_t capacity)
      : rows_(rows), cols_(cols), type_(type), capacity_(capacity) {}
  MatPool(const MatPool&) = delete;
  MatPool& operator=(const MatPool&) = delete;

  // A rows x cols x type buffer, contents undefined.
  cv::Mat Take() {
    std::lock_guard<std::mutex> lock(mu_);
    const size_t count = buffers_.size();
    for (size_t k = 0; k < count; ++k) {
      cv::Mat& buffer = buffers_[(next_ + k) % count];
      if (OnlyPoolHolds(buffer)) {
        next_ = (next_ + k + 1) % count;
        return buffer;
      }
    }
    cv::Mat buffer(rows_, cols_, type_);
    if (count < capacity_) buffers_.push_back(buffer);
    return buffer;
  }
  // Take() filled with zeros.
  cv::Mat TakeZeros() {
    cv::Mat buffer = Take();
    buffer.setTo(cv::Scalar::all(0));
    return buffer;
  }
  bool Fits(int rows, int cols, int type) const {
    return rows == rows_ && cols == cols_ && type == type_;
  }
  // Whether `m` views one of the pool's buffers (which then counts one reference more).
  bool Owns(const cv::Mat& m) const {
    std::lock_guard<std::mutex> lock(mu_);
    for (const cv::Mat& buffer : buffers_) {
      if (buffer.u == m.u) return m.u != nullptr;
    }
    return false;
  }
  // Buffers pooled, and of those the ones in use now.
  size_t pooled() const {
    std::lock_guard<std::mutex> lock(mu_);
    return buffers_.size();
  }
  size_t in_use() const {
    std::lock_guard<std::mutex> lock(mu_);
    size_t used = 0;
    for (const cv::Mat& buffer : buffers_) used += OnlyPoolHolds(buffer) ? 0 : 1;
    return used;
  }

 private:
  // cv::Mat counts its references atomically (CV_XADD); a count of one is the pool's own, and
  // no one can add a reference without holding one.
  static bool OnlyPoolHolds(const cv::Mat& buffer) {
    return buffer.u != nullptr && __atomic_load_n(&buffer.u->refcount, __ATOMIC_ACQUIRE) == 1;
  }

  const int rows_, cols_, type_;
  const size_t capacity_;
  mutable std::mutex mu_;
  std::vector<cv::Mat> buffers_;
  size_t next_ = 0;
};

}  // namespace irmosaic
