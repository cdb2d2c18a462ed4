// Bad input to FrameSource (issue 11's bad-input matrix, image sequences and frame lists): each
// is an InputError naming the path and the fix, or a kBadFrame the run can skip.
#include "irmosaic/frame_source.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "irmosaic/error.h"

namespace irmosaic {
namespace {

namespace fs = std::filesystem;

fs::path FreshDir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() /
                       ("irmosaic_frame_source_test_" + std::to_string(::getpid()) + "_" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

void WriteText(const fs::path& path, const std::string& text) {
  std::ofstream(path, std::ios::binary | std::ios::trunc) << text;
}

// The message of the InputError FrameSource::Open throws, or "" if it opens.
std::string OpenError(const std::string& path, const FrameSource::Options& options = {}) {
  try {
    FrameSource::Open(path, options);
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}

TEST(FrameSourceTest, MissingPathEmptyFolderAndBadRateAreInputErrors) {
  const fs::path dir = FreshDir("open");
  const std::string missing = OpenError((dir / "nothing.mp4").string());
  EXPECT_NE(missing.find("nothing.mp4"), std::string::npos) << missing;
  EXPECT_NE(missing.find("no such file"), std::string::npos) << missing;

  WriteText(dir / "notes.txt", "not an image");  // A folder with no images in it.
  const std::string empty = OpenError(dir.string());
  EXPECT_NE(empty.find("holds no images"), std::string::npos) << empty;

  cv::imwrite((dir / "a.png").string(), cv::Mat(8, 8, CV_8U, cv::Scalar(1)));
  FrameSource::Options zero_fps;
  zero_fps.fps = 0.0;
  EXPECT_NE(OpenError(dir.string(), zero_fps).find("frame rate"), std::string::npos);
  FrameSource::Options nan_t0;
  nan_t0.t0_s = std::nan("");
  EXPECT_NE(OpenError(dir.string(), nan_t0), "");
}

TEST(FrameSourceTest, VideoThatIsNotAVideoIsAnInputErrorNamingTheFix) {
  const fs::path dir = FreshDir("video");
  WriteText(dir / "garbage.mp4", std::string(4096, '\x5a'));
  const std::string message = OpenError((dir / "garbage.mp4").string());
  EXPECT_NE(message.find("garbage.mp4"), std::string::npos) << message;
  EXPECT_NE(message.find("ffmpeg"), std::string::npos) << message;
}

TEST(FrameSourceTest, BadFrameListsNameTheLine) {
  const fs::path dir = FreshDir("csv");
  struct Case {
    const char* name;
    std::string text;
    std::string expect;  // Must appear in the message, with the file name and line.
  };
  const std::vector<Case> cases = {
      {"header.csv", "frame,time,path\n0,0,a.png\n", "header.csv:1"},
      {"fields.csv", "index,time_s,file\n0,0.0\n", "fields.csv:2"},
      {"number.csv", "index,time_s,file\n0,abc,a.png\n", "not a number"},
      {"nan.csv", "index,time_s,file\n0,nan,a.png\n", "not a number"},
      {"index.csv", "index,time_s,file\n1.5,0,a.png\n", "not a number"},
      {"order.csv", "index,time_s,file\n0,0.04,a.png\n1,0.04,b.png\n", "order.csv:3"},
      {"back.csv", "index,time_s,file\n3,0,a.png\n2,0.04,b.png\n", "must increase"},
      {"empty.csv", "", "no frames"},
      {"header_only.csv", "index,time_s,file\r\n# nothing else\n", "no frames"},
  };
  for (const Case& c : cases) {
    WriteText(dir / c.name, c.text);
    const std::string message = OpenError((dir / c.name).string());
    EXPECT_NE(message.find(c.name), std::string::npos) << c.name << ": " << message;
    EXPECT_NE(message.find(c.expect), std::string::npos) << c.name << ": " << message;
    EXPECT_NE(message.find("Fix:"), std::string::npos) << c.name << ": " << message;
  }
}

TEST(FrameSourceTest, UnreadableImageInASequenceIsABadFrameAndTheSequenceGoesOn) {
  const fs::path dir = FreshDir("sequence");
  cv::imwrite((dir / "f0.png").string(), cv::Mat(16, 20, CV_16U, cv::Scalar(3000)));
  WriteText(dir / "f1.png", "\x89PNG\r\n\x1a\n truncated");  // A PNG signature, then nothing.
  cv::imwrite((dir / "f2.png").string(), cv::Mat(16, 20, CV_8U, cv::Scalar(7)));  // Other depth.
  auto source = FrameSource::Open(dir.string());
  ASSERT_EQ(source->size(), 3);
  SourceFrame frame;
  std::string problem;
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kFrame);
  EXPECT_EQ(frame.index, 0);
  EXPECT_EQ(frame.image.type(), CV_16U);
  EXPECT_EQ(frame.image.at<uint16_t>(5, 5), 3000);
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kBadFrame);
  EXPECT_EQ(frame.index, 1);
  EXPECT_DOUBLE_EQ(frame.time_s, 1.0 / 25.0);
  EXPECT_NE(problem.find("f1.png"), std::string::npos) << problem;
  // Mixed bit depths pass through as read; the Mosaicker refuses a frame of another depth
  // (mosaicker_test BadFramesAreSkippedWithReasonsAndTheRunGoesOn).
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kFrame);
  EXPECT_EQ(frame.index, 2);
  EXPECT_EQ(frame.image.type(), CV_8U);
  EXPECT_EQ(source->Next(&frame, &problem), FrameSource::Status::kEnd);
}

TEST(FrameSourceTest, FrameListWithAMissingFileSkipsOnlyThatFrame) {
  const fs::path dir = FreshDir("list");
  cv::imwrite((dir / "a.png").string(), cv::Mat(8, 8, CV_8UC3, cv::Scalar(10, 20, 30)));
  cv::imwrite((dir / "c.png").string(), cv::Mat(8, 8, CV_8U, cv::Scalar(9)));
  WriteText(dir / "frames.csv", "index,time_s,file\n0,0.0,a.png\n5,0.2,b.png\n9,0.36,c.png\n");
  auto source = FrameSource::Open((dir / "frames.csv").string());
  SourceFrame frame;
  std::string problem;
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kFrame);
  EXPECT_EQ(frame.image.channels(), 1);  // Colour is converted to gray.
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kBadFrame);
  EXPECT_EQ(frame.index, 5);
  EXPECT_DOUBLE_EQ(frame.time_s, 0.2);
  EXPECT_NE(problem.find("b.png"), std::string::npos) << problem;
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kFrame);
  EXPECT_EQ(frame.index, 9);
  EXPECT_EQ(source->Next(&frame, &problem), FrameSource::Status::kEnd);
}

}  // namespace
}  // namespace irmosaic
