// Frame images kept on disk instead of memory (src/image_spill.h): exact round trips, slots
// reused only when free, concurrent use, and a full disk that costs memory, not data.
#include "../src/image_spill.h"

#include <gtest/gtest.h>
#include <sys/resource.h>

#include <atomic>
#include <csignal>
#include <filesystem>
#include <opencv2/core.hpp>
#include <thread>
#include <vector>

namespace irmosaic {
namespace {

namespace fs = std::filesystem;

fs::path TestDir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() /
                       ("irmosaic_image_spill_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

cv::Mat RandomImage(int type, int seed) {
  cv::Mat image(512, 640, type);
  cv::RNG rng(static_cast<uint64_t>(seed) + 1);
  rng.fill(image, cv::RNG::UNIFORM, 0, type == CV_32F ? 1.0 : 65535.0);
  return image;
}

bool Identical(const cv::Mat& a, const cv::Mat& b) {
  return a.size() == b.size() && a.type() == b.type() &&
         cv::countNonZero(cv::Mat(a != b).reshape(1)) == 0;
}

TEST(ImageSpillTest, ImagesComeBackBitForBitInEveryDepth) {
  for (const int type : {CV_8U, CV_16U, CV_32F}) {
    const fs::path dir = TestDir("depth" + std::to_string(type));
    ImageSpill spill(dir.string());
    std::vector<cv::Mat> images;
    std::vector<std::shared_ptr<const ImageSpill::Handle>> handles;
    for (int k = 0; k < 5; ++k) {
      images.push_back(RandomImage(type, k));
      handles.push_back(spill.Put(images.back()));
      ASSERT_NE(handles.back(), nullptr) << spill.error();
    }
    for (int k = 4; k >= 0; --k) {
      EXPECT_TRUE(Identical(spill.Get(*handles[k]), images[k]))
          << "type " << type << " image " << k;
    }
    EXPECT_EQ(spill.stored(), 5u);
    EXPECT_EQ(spill.bytes_per_image(), images[0].total() * images[0].elemSize());
    // Nothing is linked into the folder: the file goes with the process.
    EXPECT_TRUE(fs::is_empty(dir));
    fs::remove_all(dir);
  }
}

TEST(ImageSpillTest, AViewIsStoredAsItsOwnPixels) {
  const fs::path dir = TestDir("view");
  ImageSpill spill(dir.string());
  const cv::Mat big = RandomImage(CV_16U, 7);
  const cv::Mat first = big(cv::Rect(0, 0, 320, 256)).clone();
  ASSERT_NE(spill.Put(first), nullptr);
  const cv::Mat view = big(cv::Rect(100, 50, 320, 256));  // Not continuous.
  ASSERT_FALSE(view.isContinuous());
  const auto handle = spill.Put(view);
  ASSERT_NE(handle, nullptr) << spill.error();
  EXPECT_TRUE(Identical(spill.Get(*handle), view));
  fs::remove_all(dir);
}

TEST(ImageSpillTest, ASlotIsReusedOnlyAfterItsLastHandleGoes) {
  const fs::path dir = TestDir("reuse");
  ImageSpill spill(dir.string());
  const cv::Mat a = RandomImage(CV_16U, 1), b = RandomImage(CV_16U, 2), c = RandomImage(CV_16U, 3);
  auto ha = spill.Put(a);
  auto hb = spill.Put(b);
  ASSERT_NE(ha, nullptr);
  ASSERT_NE(hb, nullptr);
  auto ha_copy = ha;  // A solve holding the frame's handle.
  ha.reset();
  auto hc = spill.Put(c);
  ASSERT_NE(hc, nullptr);
  EXPECT_NE(hc->slot(), ha_copy->slot()) << "a slot still referenced was written over";
  EXPECT_TRUE(Identical(spill.Get(*ha_copy), a));
  EXPECT_EQ(spill.slots(), 3u);
  ha_copy.reset();
  auto hd = spill.Put(b);
  ASSERT_NE(hd, nullptr);
  EXPECT_EQ(spill.slots(), 3u) << "the freed slot was not reused";
  EXPECT_TRUE(Identical(spill.Get(*hc), c));
  EXPECT_TRUE(Identical(spill.Get(*hd), b));
  EXPECT_EQ(spill.stored(), 3u);
  fs::remove_all(dir);
}

TEST(ImageSpillTest, AnotherSizeOrTypeIsRefusedWithoutHarm) {
  const fs::path dir = TestDir("size");
  ImageSpill spill(dir.string());
  const cv::Mat a = RandomImage(CV_16U, 1);
  const auto ha = spill.Put(a);
  ASSERT_NE(ha, nullptr);
  EXPECT_EQ(spill.Put(RandomImage(CV_8U, 2)), nullptr);
  EXPECT_EQ(spill.Put(cv::Mat(10, 10, CV_16U, cv::Scalar(3))), nullptr);
  EXPECT_EQ(spill.Put(cv::Mat()), nullptr);
  EXPECT_TRUE(Identical(spill.Get(*ha), a));
  fs::remove_all(dir);
}

TEST(ImageSpillTest, AMissingFolderIsAnErrorNotACrash) {
  ImageSpill spill((fs::temp_directory_path() / "irmosaic_no_such_folder" / "deeper").string());
  EXPECT_EQ(spill.Put(RandomImage(CV_16U, 1)), nullptr);
  EXPECT_NE(spill.error().find("cannot create the frame image file"), std::string::npos)
      << spill.error();
  EXPECT_NE(spill.error().find("irmosaic_no_such_folder"), std::string::npos) << spill.error();
  EXPECT_EQ(spill.stored(), 0u);
}

// A full disk, as the file size limit stands for it: the writes past it fail, Put says so,
// and the images stored before stay readable.
TEST(ImageSpillTest, AFullDiskRefusesNewImagesAndKeepsTheStoredOnes) {
  const fs::path dir = TestDir("full");
  ImageSpill spill(dir.string());
  const cv::Mat a = RandomImage(CV_16U, 1), b = RandomImage(CV_16U, 2);
  const size_t bytes = a.total() * a.elemSize();
  const auto ha = spill.Put(a);
  ASSERT_NE(ha, nullptr);
  rlimit old_limit{};
  ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &old_limit), 0);
  void (*old_handler)(int) = std::signal(SIGXFSZ, SIG_IGN);
  rlimit limit = old_limit;
  limit.rlim_cur = static_cast<rlim_t>(bytes + bytes / 2);  // Room for 1.5 images.
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &limit), 0);
  const auto hb = spill.Put(b);
  const std::string error = spill.error();
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &old_limit), 0);
  std::signal(SIGXFSZ, old_handler);
  EXPECT_EQ(hb, nullptr);
  EXPECT_NE(error.find("cannot write a frame image"), std::string::npos) << error;
  EXPECT_EQ(spill.stored(), 1u);
  EXPECT_TRUE(Identical(spill.Get(*ha), a));
  // Room again: the next image goes in (into the slot the failed write left free).
  const auto hc = spill.Put(b);
  ASSERT_NE(hc, nullptr) << spill.error();
  EXPECT_TRUE(Identical(spill.Get(*hc), b));
  EXPECT_EQ(spill.slots(), 2u);
  fs::remove_all(dir);
}

TEST(ImageSpillTest, ConcurrentPutsAndGetsKeepEveryImage) {
  const fs::path dir = TestDir("threads");
  ImageSpill spill(dir.string());
  constexpr int kThreads = 4, kRounds = 60;
  std::atomic<int> mismatches{0}, failures{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&, t] {
      std::vector<std::pair<cv::Mat, std::shared_ptr<const ImageSpill::Handle>>> kept;
      for (int k = 0; k < kRounds; ++k) {
        cv::Mat image(64, 80, CV_16U, cv::Scalar(t * 1000 + k));
        auto handle = spill.Put(image);
        if (!handle) {
          ++failures;
          continue;
        }
        kept.emplace_back(image, handle);
        if (kept.size() > 5) kept.erase(kept.begin());  // Slots freed and reused meanwhile.
        for (const auto& [expected, h] : kept) {
          if (!Identical(spill.Get(*h), expected)) ++mismatches;
        }
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  EXPECT_EQ(failures.load(), 0) << spill.error();
  EXPECT_EQ(mismatches.load(), 0);
  EXPECT_EQ(spill.stored(), 0u);
  EXPECT_LE(spill.slots(), static_cast<size_t>(kThreads * 6));
  fs::remove_all(dir);
}

}  // namespace
}  // namespace irmosaic
