#pragma once

#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>
#include <string>

#include "irmosaic/export.h"

namespace irmosaic {

// One frame read from a source.
struct SourceFrame {
  int64_t index = 0;
  double time_s = 0.0;
  cv::Mat image;     // One channel, CV_8U, CV_16U or CV_32F (colour is converted to gray).
  std::string name;  // File name or "video frame N", for messages.
};

// Frames from a video file (OpenCV), a folder of images, or a frame list CSV
// (index,time_s,file; relative files against the CSV's folder, as `irmosaic synth` writes).
class IRMOSAIC_EXPORT FrameSource {
 public:
  struct Options {
    double fps = 25.0;  // Frame rate for videos and folders (time = t0 + i / fps).
    double t0_s = 0.0;  // Time of the first frame for videos and folders.
  };
  // Throws InputError naming the path and the fix (missing, unsupported, empty, a video with
  // no decodable frame).
  static std::unique_ptr<FrameSource> Open(const std::string& path, const Options& options);
  static std::unique_ptr<FrameSource> Open(const std::string& path) { return Open(path, {}); }
  virtual ~FrameSource() = default;

  enum class Status { kFrame, kEnd, kBadFrame };
  // Next frame. kBadFrame: this one could not be read, or its size or bit depth differs from
  // the first frame's (`frame->index`, `frame->name` and `*problem` say which and why); the
  // source moves on, so the caller can skip it and continue. kEnd with a non-empty `*problem`:
  // the stream ended early (a video shorter than its header says), a warning to show.
  // `*problem` is cleared otherwise.
  virtual Status Next(SourceFrame* frame, std::string* problem) = 0;
  // Total frames if known, else -1.
  virtual int64_t size() const = 0;
  // Moves so that the next frame returned is the first with index > `index`.
  virtual void SkipThrough(int64_t index) = 0;
};

// Converts an image to one channel of 8-bit, 16-bit or float, as the pipeline takes it.
IRMOSAIC_EXPORT cv::Mat ToPipelineImage(const cv::Mat& image);

}  // namespace irmosaic
