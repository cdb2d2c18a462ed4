// Bad input to FrameSource (issue 11's bad-input matrix, image sequences and frame lists): each
// is an InputError naming the path and the fix, or a kBadFrame the run can skip.
#include "irmosaic/frame_source.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>
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
  // A frame of another bit depth than the first is skipped, naming both depths and the fix.
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kBadFrame);
  EXPECT_EQ(frame.index, 2);
  EXPECT_NE(problem.find("f2.png"), std::string::npos) << problem;
  EXPECT_NE(problem.find("8-bit but the stream started at 20x16 16-bit"), std::string::npos)
      << problem;
  EXPECT_NE(problem.find("Fix:"), std::string::npos) << problem;
  EXPECT_EQ(source->Next(&frame, &problem), FrameSource::Status::kEnd);
  EXPECT_EQ(problem, "");
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

TEST(FrameSourceTest, MixedSizesInASequenceAreSkippedNamingTheFile) {
  const fs::path dir = FreshDir("sizes");
  cv::imwrite((dir / "f0.png").string(), cv::Mat(16, 20, CV_8U, cv::Scalar(1)));
  cv::imwrite((dir / "f1.png").string(), cv::Mat(32, 40, CV_8U, cv::Scalar(2)));
  cv::imwrite((dir / "f2.png").string(), cv::Mat(16, 20, CV_8U, cv::Scalar(3)));
  auto source = FrameSource::Open(dir.string());
  SourceFrame frame;
  std::string problem;
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kFrame);
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kBadFrame);
  EXPECT_EQ(frame.index, 1);
  EXPECT_NE(problem.find("f1.png (frame 1) is 40x32 8-bit but the stream started at 20x16"),
            std::string::npos)
      << problem;
  ASSERT_EQ(source->Next(&frame, &problem), FrameSource::Status::kFrame);  // The run goes on.
  EXPECT_EQ(frame.index, 2);
  EXPECT_EQ(frame.image.at<uint8_t>(0, 0), 3);
}

// Videos: MJPEG in AVI written by OpenCV's VideoWriter, then damaged byte by byte. Frame i is
// uniform gray 20 * i + 10 with a bright square, so each frame read can be told apart.
constexpr int kVideoFrames = 10;
uint8_t VideoFrameValue(int i) { return static_cast<uint8_t>(20 * i + 10); }

void WriteVideo(const fs::path& path) {
  cv::VideoWriter writer(path.string(), cv::VideoWriter::fourcc('M', 'J', 'P', 'G'), 25.0,
                         cv::Size(64, 48), false);
  ASSERT_TRUE(writer.isOpened()) << path;
  for (int i = 0; i < kVideoFrames; ++i) {
    cv::Mat image(48, 64, CV_8U, cv::Scalar(VideoFrameValue(i)));
    image(cv::Rect(4 + 4 * i, 8, 8, 8)).setTo(255);
    writer.write(image);
  }
}

std::string ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), {});
}

// Offset and size of each frame's JPEG in an AVI ('00dc' chunks starting with FF D8).
std::vector<std::pair<size_t, size_t>> JpegChunks(const std::string& avi) {
  std::vector<std::pair<size_t, size_t>> chunks;
  for (size_t at = avi.find("00dc"); at != std::string::npos; at = avi.find("00dc", at + 4)) {
    if (at + 10 > avi.size()) break;
    const size_t size = static_cast<uint8_t>(avi[at + 4]) |
                        static_cast<size_t>(static_cast<uint8_t>(avi[at + 5])) << 8 |
                        static_cast<size_t>(static_cast<uint8_t>(avi[at + 6])) << 16;
    if (avi.compare(at + 8, 2, "\xff\xd8") == 0) chunks.push_back({at + 8, size});
  }
  return chunks;
}

// Reads the whole source: index -> mean gray of the frame (-1 for a bad frame).
struct ReadAll {
  std::vector<std::pair<int64_t, double>> frames;
  std::vector<std::string> problems;
  std::string end_warning;
};
ReadAll ReadEverything(FrameSource* source) {
  ReadAll all;
  SourceFrame frame;
  std::string problem;
  for (int guard = 0; guard < 1000; ++guard) {
    const FrameSource::Status status = source->Next(&frame, &problem);
    if (status == FrameSource::Status::kEnd) {
      all.end_warning = problem;
      break;
    }
    if (status == FrameSource::Status::kBadFrame) {
      all.frames.push_back({frame.index, -1.0});
      all.problems.push_back(problem);
      continue;
    }
    EXPECT_EQ(frame.image.channels(), 1);
    EXPECT_EQ(frame.image.size(), cv::Size(64, 48));
    EXPECT_DOUBLE_EQ(frame.time_s, frame.index / 25.0);
    all.frames.push_back({frame.index, cv::mean(frame.image)[0]});
  }
  return all;
}

// Mean gray of video frame i as written (the square included).
double WrittenMean(int i) { return (VideoFrameValue(i) * (64.0 * 48 - 64) + 255.0 * 64) / 3072; }

TEST(FrameSourceTest, VideoFramesKeepTheirIndicesAndTimes) {
  const fs::path dir = FreshDir("video_ok");
  WriteVideo(dir / "v.avi");
  auto source = FrameSource::Open((dir / "v.avi").string());
  EXPECT_EQ(source->size(), kVideoFrames);
  const ReadAll all = ReadEverything(source.get());
  ASSERT_EQ(all.frames.size(), static_cast<size_t>(kVideoFrames));
  for (int i = 0; i < kVideoFrames; ++i) {
    EXPECT_EQ(all.frames[i].first, i);
    EXPECT_NEAR(all.frames[i].second, WrittenMean(i), 3.0) << i;  // JPEG: a few gray levels.
  }
  EXPECT_EQ(all.end_warning, "");
}

TEST(FrameSourceTest, VideoWithZeroFramesIsAnInputError) {
  const fs::path dir = FreshDir("video_empty");
  WriteVideo(dir / "v.avi");
  const std::string avi = ReadBytes(dir / "v.avi");
  const auto chunks = JpegChunks(avi);
  ASSERT_EQ(chunks.size(), static_cast<size_t>(kVideoFrames));
  // The headers, and not one frame.
  WriteText(dir / "empty.avi", avi.substr(0, chunks[0].first - 8));
  const std::string message = OpenError((dir / "empty.avi").string());
  EXPECT_NE(message.find("empty.avi"), std::string::npos) << message;
  EXPECT_NE(message.find("no frame that can be decoded"), std::string::npos) << message;
  EXPECT_NE(message.find("Fix:"), std::string::npos) << message;
}

TEST(FrameSourceTest, VideoOfAnUnsupportedCodecIsAnInputError) {
  const fs::path dir = FreshDir("video_codec");
  WriteVideo(dir / "v.avi");
  std::string avi = ReadBytes(dir / "v.avi");
  // A valid AVI whose codec tag names no decoder FFmpeg has ('MJPG' -> 'QQQQ' everywhere).
  int replaced = 0;
  for (size_t at = avi.find("MJPG"); at != std::string::npos; at = avi.find("MJPG", at)) {
    avi.replace(at, 4, "QQQQ");
    ++replaced;
  }
  ASSERT_GE(replaced, 1);
  WriteText(dir / "codec.avi", avi);
  const std::string message = OpenError((dir / "codec.avi").string());
  EXPECT_NE(message.find("codec.avi"), std::string::npos) << message;
  EXPECT_NE(message.find("ffmpeg"), std::string::npos) << message;
}

TEST(FrameSourceTest, TruncatedVideoEndsAtTheCutWithAWarning) {
  const fs::path dir = FreshDir("video_cut");
  WriteVideo(dir / "v.avi");
  const std::string avi = ReadBytes(dir / "v.avi");
  const auto chunks = JpegChunks(avi);
  ASSERT_EQ(chunks.size(), static_cast<size_t>(kVideoFrames));
  WriteText(dir / "cut.avi", avi.substr(0, chunks[6].first + chunks[6].second / 2));  // In 6.
  auto source = FrameSource::Open((dir / "cut.avi").string());
  const ReadAll all = ReadEverything(source.get());
  ASSERT_EQ(all.frames.size(), 6u);
  for (int i = 0; i < 6; ++i) EXPECT_NEAR(all.frames[i].second, WrittenMean(i), 3.0) << i;
  EXPECT_NE(all.end_warning.find("cut.avi ends after 6 frames but its header announces 10"),
            std::string::npos)
      << all.end_warning;
}

TEST(FrameSourceTest, CorruptFrameMidVideoIsSkippedAndTheRestKeepTheirIndices) {
  const fs::path dir = FreshDir("video_corrupt");
  WriteVideo(dir / "v.avi");
  std::string avi = ReadBytes(dir / "v.avi");
  const auto chunks = JpegChunks(avi);
  ASSERT_EQ(chunks.size(), static_cast<size_t>(kVideoFrames));
  // Frame 5: every byte zeroed (the decoder finds no JPEG). Frame 2: 16 bytes of its
  // entropy-coded data zeroed (FFmpeg conceals it and returns a damaged frame: not detectable
  // through OpenCV, so it is passed on; registration's checks are what guard against it).
  std::fill_n(avi.begin() + static_cast<std::ptrdiff_t>(chunks[5].first), chunks[5].second, '\0');
  const size_t sos = avi.find("\xff\xda", chunks[2].first);  // Start of scan: entropy data.
  ASSERT_LT(sos + 40, chunks[2].first + chunks[2].second);
  std::fill_n(avi.begin() + static_cast<std::ptrdiff_t>(sos + 20), 16, '\0');
  WriteText(dir / "corrupt.avi", avi);
  auto source = FrameSource::Open((dir / "corrupt.avi").string());
  const ReadAll all = ReadEverything(source.get());
  ASSERT_EQ(all.frames.size(), static_cast<size_t>(kVideoFrames));
  for (int i = 0; i < kVideoFrames; ++i) {
    EXPECT_EQ(all.frames[i].first, i);
    if (i == 5) {
      EXPECT_EQ(all.frames[i].second, -1.0);
    } else if (i != 2) {
      EXPECT_NEAR(all.frames[i].second, WrittenMean(i), 3.0) << i;  // Not shifted by one.
    }
  }
  ASSERT_EQ(all.problems.size(), 1u);
  EXPECT_NE(all.problems[0].find("corrupt.avi frame 5"), std::string::npos) << all.problems[0];
  EXPECT_EQ(all.end_warning, "");

  // Resuming skips through the lost frame without losing count.
  auto again = FrameSource::Open((dir / "corrupt.avi").string());
  again->SkipThrough(6);
  SourceFrame frame;
  std::string problem;
  ASSERT_EQ(again->Next(&frame, &problem), FrameSource::Status::kFrame);
  EXPECT_EQ(frame.index, 7);
  EXPECT_NEAR(cv::mean(frame.image)[0], WrittenMean(7), 3.0);
}

TEST(FrameSourceTest, FrameSizeChangingMidVideoKeepsTheStreamSize) {
  // A raw MJPEG stream whose frame 5 is a 32x24 JPEG among 64x48 ones. OpenCV's FFmpeg backend
  // delivers every frame at the stream's first size (measured), so the frame reaches the
  // pipeline at 64x48, with its index; image sequences, where sizes do reach us, are checked
  // in MixedSizesInASequenceAreSkippedNamingTheFile.
  const fs::path dir = FreshDir("video_size");
  std::ofstream out(dir / "sizes.mjpeg", std::ios::binary);
  for (int i = 0; i < kVideoFrames; ++i) {
    const cv::Size size = i == 5 ? cv::Size(32, 24) : cv::Size(64, 48);
    std::vector<uchar> jpeg;
    ASSERT_TRUE(cv::imencode(".jpg", cv::Mat(size, CV_8U, cv::Scalar(VideoFrameValue(i))), jpeg));
    out.write(reinterpret_cast<const char*>(jpeg.data()),
              static_cast<std::streamsize>(jpeg.size()));
  }
  out.close();
  auto source = FrameSource::Open((dir / "sizes.mjpeg").string());
  const ReadAll all = ReadEverything(source.get());  // Asserts 64x48 for every frame.
  ASSERT_EQ(all.frames.size(), static_cast<size_t>(kVideoFrames));
  for (int i = 0; i < kVideoFrames; ++i) {
    EXPECT_EQ(all.frames[i].first, i);
    if (i != 5) {
      EXPECT_NEAR(all.frames[i].second, VideoFrameValue(i), 3.0) << i;
    }
  }
}

}  // namespace
}  // namespace irmosaic
