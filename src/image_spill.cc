#include "image_spill.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>

namespace irmosaic {

struct ImageSpill::State {
  std::mutex mu;
  std::string directory;
  int fd = -1;
  bool open_failed = false;
  int rows = 0, cols = 0, type = -1;  // Of the first image; 0 x 0 until then.
  size_t bytes = 0;
  std::vector<size_t> free_slots;
  size_t next_slot = 0;
  size_t stored = 0;
  std::string error;

  ~State() {
    if (fd >= 0) ::close(fd);
  }
  void FailLocked(const std::string& what) {
    if (error.empty()) error = what;
  }
  // Opens the file (under mu). False when it cannot; the reason is in error.
  bool OpenLocked() {
    if (fd >= 0) return true;
    if (open_failed) return false;
    const std::string dir = directory.empty() ? "." : directory;
#ifdef O_TMPFILE
    fd = ::open(dir.c_str(), O_TMPFILE | O_RDWR | O_CLOEXEC, 0600);
#endif
    if (fd < 0) {
      // File systems without O_TMPFILE: a unique name, unlinked at once.
      std::string name = (std::filesystem::path(dir) / ".irmosaic-images-XXXXXX").string();
      fd = ::mkstemp(name.data());
      if (fd >= 0) {
        ::unlink(name.c_str());
        ::fcntl(fd, F_SETFD, FD_CLOEXEC);
      }
    }
    if (fd < 0) {
      open_failed = true;
      FailLocked("cannot create the frame image file in " + dir + ": " + std::strerror(errno));
      return false;
    }
    return true;
  }
};

ImageSpill::Handle::~Handle() {
  std::lock_guard<std::mutex> lock(state_->mu);
  state_->free_slots.push_back(slot_);
  --state_->stored;
}

ImageSpill::ImageSpill(std::string directory) : state_(std::make_shared<State>()) {
  state_->directory = std::move(directory);
}

ImageSpill::~ImageSpill() = default;

namespace {

// pwrite / pread of the whole range (they may do part of it); false with errno set.
bool WriteAll(int fd, const unsigned char* data, size_t size, off_t offset) {
  while (size > 0) {
    const ssize_t n = ::pwrite(fd, data, size, offset);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      if (n == 0) errno = ENOSPC;
      return false;
    }
    data += n, size -= static_cast<size_t>(n), offset += n;
  }
  return true;
}

bool ReadAll(int fd, unsigned char* data, size_t size, off_t offset) {
  while (size > 0) {
    const ssize_t n = ::pread(fd, data, size, offset);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      if (n == 0) errno = EIO;  // Past the end: the slot was never written.
      return false;
    }
    data += n, size -= static_cast<size_t>(n), offset += n;
  }
  return true;
}

}  // namespace

std::shared_ptr<const ImageSpill::Handle> ImageSpill::Put(const cv::Mat& image) {
  if (image.empty() || image.dims != 2) return nullptr;
  State& s = *state_;
  size_t slot = 0;
  int fd = -1;
  {
    std::lock_guard<std::mutex> lock(s.mu);
    if (s.bytes == 0) {
      s.rows = image.rows, s.cols = image.cols, s.type = image.type();
      s.bytes = image.total() * image.elemSize();
    } else if (image.rows != s.rows || image.cols != s.cols || image.type() != s.type) {
      return nullptr;  // Another camera's frame: the caller keeps it in memory.
    }
    if (!s.OpenLocked()) return nullptr;
    fd = s.fd;
    if (!s.free_slots.empty()) {
      slot = s.free_slots.back();
      s.free_slots.pop_back();
    } else {
      slot = s.next_slot++;
    }
    ++s.stored;
  }
  // The handle owns the slot from here: on failure it goes back to the free list with it.
  auto handle = std::make_shared<const Handle>(state_, slot);
  const cv::Mat continuous = image.isContinuous() ? image : image.clone();
  const off_t offset = static_cast<off_t>(slot * s.bytes);
  if (!WriteAll(fd, continuous.data, s.bytes, offset)) {
    const int code = errno;
    std::lock_guard<std::mutex> lock(s.mu);
    s.FailLocked("cannot write a frame image to the file in " + s.directory + ": " +
                 std::strerror(code));
    return nullptr;
  }
  return handle;
}

cv::Mat ImageSpill::Get(const Handle& handle) {
  State& s = *state_;
  if (handle.state_ != state_) return {};
  cv::Mat image;
  int fd = -1;
  {
    std::lock_guard<std::mutex> lock(s.mu);
    fd = s.fd;
  }
  // A fresh buffer, not a pooled one: a pool's reuse is ordered only by OpenCV's reference
  // count, which ThreadSanitizer cannot see, and images are read back ~2 times per frame.
  image.create(s.rows, s.cols, s.type);
  if (!ReadAll(fd, image.data, s.bytes, static_cast<off_t>(handle.slot() * s.bytes))) {
    const int code = errno;
    std::lock_guard<std::mutex> lock(s.mu);
    s.FailLocked("cannot read a frame image back from the file in " + s.directory + ": " +
                 std::strerror(code));
    return {};
  }
  return image;
}

std::string ImageSpill::error() const {
  std::lock_guard<std::mutex> lock(state_->mu);
  return state_->error;
}

size_t ImageSpill::stored() const {
  std::lock_guard<std::mutex> lock(state_->mu);
  return state_->stored;
}

size_t ImageSpill::slots() const {
  std::lock_guard<std::mutex> lock(state_->mu);
  return state_->next_slot;
}

size_t ImageSpill::bytes_per_image() const {
  std::lock_guard<std::mutex> lock(state_->mu);
  return state_->bytes;
}

}  // namespace irmosaic
