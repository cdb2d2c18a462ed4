#pragma once
// Private helper (src/map_fusion.cc): frame images held for a long time but seldom read (the
// fusion keeps each frame's image for a window of ~300 frames so that a solve can re-render
// it) are kept in an unnamed file on disk instead of memory, and read back when needed. The
// file lives in a folder the caller names (the store's), is never linked into it (O_TMPFILE;
// otherwise a unique name unlinked at once), so it disappears with the process, crash or not.
// Not installed.
#include <cstddef>
#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace irmosaic {

class ImageSpill {
 public:
  struct State;
  // A stored image: a slot of the file, free for another image again when the last reference
  // to the handle goes (even after the ImageSpill itself).
  class Handle {
   public:
    Handle(std::shared_ptr<State> state, size_t slot) : state_(std::move(state)), slot_(slot) {}
    ~Handle();
    Handle(const Handle&) = delete;
    Handle& operator=(const Handle&) = delete;
    size_t slot() const { return slot_; }

   private:
    friend class ImageSpill;
    std::shared_ptr<State> state_;
    size_t slot_;
  };

  // `directory`: where the unnamed file goes (created at the first Put).
  explicit ImageSpill(std::string directory);
  ~ImageSpill();
  ImageSpill(const ImageSpill&) = delete;
  ImageSpill& operator=(const ImageSpill&) = delete;

  // Stores a copy of `image` (any layout). Null when it cannot: the file cannot be created,
  // a write failed (disk full, file size limit), or the image's size or type differs from the
  // first one stored; error() then says why (the first failure). Thread-safe.
  std::shared_ptr<const Handle> Put(const cv::Mat& image);
  // The image stored under `handle` (of this spill), read back; empty on a read error (error()
  // says which). Thread-safe, also concurrently with Put.
  cv::Mat Get(const Handle& handle);

  std::string error() const;  // The first failure, or empty.
  size_t stored() const;      // Images stored now (handles alive).
  size_t slots() const;       // Slots the file has grown to (its size / image bytes).
  size_t bytes_per_image() const;

 private:
  std::shared_ptr<State> state_;
};

}  // namespace irmosaic
