// The fixed helper threads that register a frame's pairs beside the caller
// (src/helper_threads.h).
#include "../src/helper_threads.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <opencv2/imgproc.hpp>
#include <set>
#include <stdexcept>
#include <thread>

namespace irmosaic {
namespace {

TEST(HelperThreadsTest, ManyBatchesRunOnTheSameThreads) {
  // A thread started per batch (what std::async per frame did) would show a new thread in every
  // batch; each thread counts itself once, the first time it runs the work.
  HelperThreads helpers(1, "irm-test");
  std::atomic<int> threads_seen{0};
  std::atomic<int> runs{0};
  for (int batch = 0; batch < 200; ++batch) {
    helpers.Run(1, [&] {
      thread_local bool counted = false;
      if (!counted) {
        counted = true;
        ++threads_seen;
      }
      ++runs;
    });
  }
  EXPECT_EQ(runs.load(), 400) << "the caller and the helper each run every batch's work once";
  EXPECT_EQ(threads_seen.load(), 2) << "the caller and one helper, kept for every batch";
}

TEST(HelperThreadsTest, WorkIsSharedAndRunReturnsAfterEveryHelperFinished) {
  HelperThreads helpers(3, "irm-test");
  for (int batch = 0; batch < 50; ++batch) {
    std::atomic<int> next{0};
    std::atomic<int> done{0};
    std::mutex mu;
    std::set<std::thread::id> workers;
    helpers.Run(3, [&] {
      for (int k = next++; k < 16; k = next++) {
        // OpenCV work, as the registrar's, on each thread.
        cv::Mat image(64, 64, CV_32F, cv::Scalar(k)), half;
        cv::pyrDown(image, half);
        ASSERT_FLOAT_EQ(half.at<float>(10, 10), static_cast<float>(k));
        std::this_thread::sleep_for(std::chrono::microseconds(200));
        ++done;
      }
      std::lock_guard<std::mutex> lock(mu);
      workers.insert(std::this_thread::get_id());
    });
    EXPECT_EQ(done.load(), 16) << "Run returned before all the items were done";
    EXPECT_EQ(workers.size(), 4u) << "each of the caller and the three helpers took part";
  }
}

TEST(HelperThreadsTest, FewerHelpersThanThreadsLeaveTheOthersIdle) {
  HelperThreads helpers(3, "irm-test");
  std::atomic<int> runs{0};
  helpers.Run(1, [&] { ++runs; });
  EXPECT_EQ(runs.load(), 2);
  runs = 0;
  helpers.Run(0, [&] { ++runs; });
  EXPECT_EQ(runs.load(), 1);
  runs = 0;
  helpers.Run(10, [&] { ++runs; });  // More than there are: all of them.
  EXPECT_EQ(runs.load(), 4);
}

TEST(HelperThreadsTest, AnExceptionOfAHelperReachesTheCallerAfterAllFinished) {
  HelperThreads helpers(1, "irm-test");
  std::atomic<bool> caller_finished{false};
  const std::thread::id caller = std::this_thread::get_id();
  try {
    helpers.Run(1, [&] {
      if (std::this_thread::get_id() != caller) throw std::runtime_error("helper failed");
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      caller_finished = true;
    });
    FAIL() << "the helper's exception was lost";
  } catch (const std::runtime_error& e) {
    EXPECT_STREQ(e.what(), "helper failed");
    EXPECT_TRUE(caller_finished.load());
  }
  // The threads still work after a failed batch.
  std::atomic<int> runs{0};
  helpers.Run(1, [&] { ++runs; });
  EXPECT_EQ(runs.load(), 2);
}

}  // namespace
}  // namespace irmosaic
