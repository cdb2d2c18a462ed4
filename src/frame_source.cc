#include "irmosaic/frame_source.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <sstream>
#include <vector>

#include "irmosaic/error.h"

namespace irmosaic {
namespace fs = std::filesystem;

cv::Mat ToPipelineImage(const cv::Mat& image) {
  if (image.empty()) return image;
  cv::Mat gray = image;
  if (image.channels() == 3) cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  if (image.channels() == 4) cv::cvtColor(image, gray, cv::COLOR_BGRA2GRAY);
  if (gray.depth() == CV_8U || gray.depth() == CV_16U || gray.depth() == CV_32F) return gray;
  cv::Mat converted;
  gray.convertTo(converted, CV_32F);
  return converted;
}

namespace {

std::string DepthName(int depth) {
  return depth == CV_8U ? "8-bit" : depth == CV_16U ? "16-bit" : "float";
}

// Every frame of a stream must have the first frame's size and bit depth: the camera model and
// the store's pixel type follow the first. A frame that differs is skipped with the reason
// (OpenCV's video backends scale frames to the stream's size themselves; image sequences and
// frame lists can mix anything).
class StreamShape {
 public:
  // "" if `frame` matches the stream's first frame (remembered on the first call).
  std::string Check(const SourceFrame& frame) {
    const cv::Mat& image = frame.image;
    if (first_.empty()) {
      first_ = image.size();
      depth_ = image.depth();
      return "";
    }
    if (image.size() == first_ && image.depth() == depth_) return "";
    return frame.name + " (frame " + std::to_string(frame.index) + ") is " +
           std::to_string(image.cols) + "x" + std::to_string(image.rows) + " " +
           DepthName(image.depth()) + " but the stream started at " + std::to_string(first_.width) +
           "x" + std::to_string(first_.height) + " " + DepthName(depth_) +
           "; skipped. Fix: give every frame the size and bit depth of the first";
  }

 private:
  cv::Size first_;
  int depth_ = -1;
};

// A list of image files with their times.
class FileListSource : public FrameSource {
 public:
  struct Entry {
    int64_t index;
    double time_s;
    std::string path;
  };
  explicit FileListSource(std::vector<Entry> entries) : entries_(std::move(entries)) {}

  Status Next(SourceFrame* frame, std::string* problem) override {
    problem->clear();
    if (next_ >= entries_.size()) return Status::kEnd;
    const Entry& e = entries_[next_++];
    frame->index = e.index;
    frame->time_s = e.time_s;
    frame->name = e.path;
    frame->image = ToPipelineImage(cv::imread(e.path, cv::IMREAD_UNCHANGED));
    if (frame->image.empty()) {
      *problem = "cannot read image " + e.path + " (frame " + std::to_string(e.index) +
                 ": missing, truncated or not an image); skipped";
      return Status::kBadFrame;
    }
    *problem = shape_.Check(*frame);
    return problem->empty() ? Status::kFrame : Status::kBadFrame;
  }
  int64_t size() const override { return static_cast<int64_t>(entries_.size()); }
  void SkipThrough(int64_t index) override {
    while (next_ < entries_.size() && entries_[next_].index <= index) ++next_;
  }

 private:
  std::vector<Entry> entries_;
  size_t next_ = 0;
  StreamShape shape_;
};

// A video through OpenCV (FFmpeg). A packet the decoder rejects makes grab() fail once and the
// next grab() continue with the following frame (measured with a zeroed MJPEG frame in an AVI),
// so a failed grab followed by a good one within kMaxLostFrames is a lost frame, reported as a
// bad frame with its own index, and the frames after it keep their indices and times. Only
// kMaxLostFrames failures in a row end the stream.
class VideoSource : public FrameSource {
 public:
  static constexpr int kMaxLostFrames = 25;

  VideoSource(const std::string& path, const Options& options) : path_(path), options_(options) {
    // FFmpeg only: when it cannot read a file, OpenCV's other backends are no help for a file
    // (GStreamer, and gphoto2, which scans the USB bus for cameras and leaks what it found).
    capture_.open(path, cv::CAP_FFMPEG);
    if (!capture_.isOpened()) {
      throw InputError({path, 0, 0, ""},
                       "OpenCV cannot open this video (unsupported codec or "
                       "container, or not a video)",
                       "convert it to an image sequence or a "
                       "format FFmpeg reads, e.g. ffmpeg -i IN -c:v ffv1 OUT.mkv");
    }
    const double count = capture_.get(cv::CAP_PROP_FRAME_COUNT);
    size_ = count > 0 && count < 1e12 ? static_cast<int64_t>(count) : -1;
    capture_.set(cv::CAP_PROP_CONVERT_RGB, 0);
    // A video with no decodable frame is refused here, not reported as an empty run later.
    if (!GrabNext(&lost_pending_)) {
      throw InputError({path, 0, 0, ""},
                       "the video holds no frame that can be decoded (0 frames, or the first " +
                           std::to_string(kMaxLostFrames + 1) + " are damaged)",
                       "check the recording; convert it with ffmpeg -i IN -c:v ffv1 OUT.mkv to "
                       "see FFmpeg's own errors");
    }
    pending_ = true;
  }
  Status Next(SourceFrame* frame, std::string* problem) override {
    problem->clear();
    if (!pending_) {
      if (!GrabNext(&lost_pending_)) {
        if (size_ > 0 && next_ < size_) {
          *problem = path_ + " ends after " + std::to_string(next_) +
                     " frames but its header announces " + std::to_string(size_) +
                     " (a truncated file?); the run stops at the last frame read";
        }
        return Status::kEnd;
      }
      pending_ = true;
    }
    const int64_t i = next_++;
    frame->index = i;
    frame->time_s = options_.t0_s + static_cast<double>(i) / options_.fps;
    frame->name = path_ + " frame " + std::to_string(i);
    if (lost_pending_ > 0) {
      --lost_pending_;
      *problem = "cannot decode " + frame->name + " (damaged data in the video); skipped";
      frame->image.release();
      return Status::kBadFrame;
    }
    pending_ = false;
    cv::Mat image;
    if (!capture_.retrieve(image) || image.empty()) {
      *problem = "cannot decode " + frame->name + "; skipped";
      frame->image.release();
      return Status::kBadFrame;
    }
    frame->image = ToPipelineImage(image);
    *problem = shape_.Check(*frame);
    return problem->empty() ? Status::kFrame : Status::kBadFrame;
  }
  int64_t size() const override { return size_; }
  void SkipThrough(int64_t index) override {
    while (next_ <= index) {
      if (lost_pending_ > 0) {
        --lost_pending_;
      } else if (pending_) {
        pending_ = false;
      } else if (!GrabNext(&lost_pending_)) {
        return;
      } else {
        pending_ = true;
        continue;
      }
      ++next_;
    }
  }

 private:
  // Grabs the next decodable frame; *lost: failed grabs before it. False at the end.
  bool GrabNext(int* lost) {
    for (int k = 0; k <= kMaxLostFrames; ++k) {
      if (capture_.grab()) {
        *lost = k;
        return true;
      }
    }
    *lost = 0;
    return false;
  }

  std::string path_;
  Options options_;
  cv::VideoCapture capture_;
  int64_t size_ = -1;
  int64_t next_ = 0;      // Index of the next frame Next() returns.
  bool pending_ = false;  // A frame is grabbed and not yet returned.
  int lost_pending_ = 0;  // Lost frames to report before the pending one.
  StreamShape shape_;
};

bool IsImageFile(const fs::path& p) {
  std::string ext = p.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  return ext == ".tif" || ext == ".tiff" || ext == ".png" || ext == ".jpg" || ext == ".jpeg" ||
         ext == ".pgm" || ext == ".bmp";
}

std::vector<FileListSource::Entry> ReadFrameCsv(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    throw InputError({path, 0, 0, ""}, "cannot open the frame list",
                     "check the path and that the file is readable");
  }
  const fs::path base = fs::path(path).parent_path();
  std::vector<FileListSource::Entry> entries;
  std::string line;
  int line_number = 0;
  bool header = false;
  while (std::getline(in, line)) {
    ++line_number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty() || line[0] == '#') continue;
    if (!header) {
      if (line != "index,time_s,file") {
        throw InputError({path, line_number, 1, ""}, "the header is not 'index,time_s,file'",
                         "write the header index,time_s,file");
      }
      header = true;
      continue;
    }
    std::stringstream row(line);
    std::string index, time, file;
    if (!std::getline(row, index, ',') || !std::getline(row, time, ',') ||
        !std::getline(row, file)) {
      throw InputError({path, line_number, 0, ""}, "row does not have 3 fields",
                       "write index,time_s,file");
    }
    FileListSource::Entry e;
    try {
      size_t used = 0;
      e.index = std::stoll(index, &used);
      if (used != index.size()) throw std::invalid_argument(index);
      e.time_s = std::stod(time, &used);
      if (used != time.size() || !std::isfinite(e.time_s)) throw std::invalid_argument(time);
    } catch (const std::exception&) {
      throw InputError({path, line_number, 0, ""}, "index or time is not a number",
                       "write a whole index and a time in seconds");
    }
    if (!entries.empty() &&
        (e.index <= entries.back().index || e.time_s <= entries.back().time_s)) {
      throw InputError({path, line_number, 0, ""}, "index and time must increase from row to row",
                       "sort the frame list");
    }
    e.path = fs::path(file).is_absolute() ? file : (base / file).string();
    entries.push_back(e);
  }
  if (entries.empty()) {
    throw InputError({path, line_number, 0, ""}, "the frame list has no frames",
                     "list at least one frame after the header");
  }
  return entries;
}

}  // namespace

std::unique_ptr<FrameSource> FrameSource::Open(const std::string& path, const Options& options) {
  if (!(options.fps > 0.0) || !std::isfinite(options.t0_s)) {
    throw InputError({"--fps", 0, 0, ""}, "the frame rate must be positive", "give --fps, e.g. 25");
  }
  std::error_code ec;
  if (!fs::exists(path, ec)) {
    throw InputError({path, 0, 0, ""}, "no such file or folder", "check the frames path");
  }
  if (fs::is_directory(path, ec)) {
    std::vector<fs::path> files;
    for (const auto& entry : fs::directory_iterator(path)) {
      if (entry.is_regular_file() && IsImageFile(entry.path())) files.push_back(entry.path());
    }
    std::sort(files.begin(), files.end());
    if (files.empty()) {
      throw InputError({path, 0, 0, ""}, "the folder holds no images (.tif .png .jpg .pgm .bmp)",
                       "point --frames at the image sequence or its frames.csv");
    }
    std::vector<FileListSource::Entry> entries;
    for (size_t i = 0; i < files.size(); ++i) {
      entries.push_back(
          {static_cast<int64_t>(i), options.t0_s + i / options.fps, files[i].string()});
    }
    return std::make_unique<FileListSource>(std::move(entries));
  }
  if (fs::path(path).extension() == ".csv")
    return std::make_unique<FileListSource>(ReadFrameCsv(path));
  if (IsImageFile(path)) {
    return std::make_unique<FileListSource>(
        std::vector<FileListSource::Entry>{{0, options.t0_s, path}});
  }
  return std::make_unique<VideoSource>(path, options);
}

}  // namespace irmosaic
