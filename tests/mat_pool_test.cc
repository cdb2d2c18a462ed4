// The pool of fixed-size buffers behind held frame images and store tiles (src/mat_pool.h).
#include "../src/mat_pool.h"

#include <gtest/gtest.h>

#include <atomic>
#include <thread>
#include <vector>

namespace irmosaic {
namespace {

TEST(MatPoolTest, ABufferReturnsToThePoolWhenItsLastHolderLetsGo) {
  MatPool pool(512, 640, CV_16U, 4);
  cv::Mat a = pool.Take();
  ASSERT_EQ(a.rows, 512);
  ASSERT_EQ(a.cols, 640);
  ASSERT_EQ(a.type(), CV_16U);
  const uchar* first = a.data;
  cv::Mat view = a(cv::Rect(10, 10, 20, 20));  // A view holds it too.
  cv::Mat b = pool.Take();
  EXPECT_NE(b.data, first) << "a buffer in use was handed out again";
  EXPECT_EQ(pool.in_use(), 2u);
  a.release();
  cv::Mat c = pool.Take();
  EXPECT_NE(c.data, first) << "a buffer a view still holds was handed out again";
  view.release();
  EXPECT_EQ(pool.in_use(), 2u);  // b and c.
  cv::Mat d = pool.Take();
  EXPECT_EQ(d.data, first) << "the released buffer was not reused";
  EXPECT_EQ(pool.pooled(), 3u);
}

TEST(MatPoolTest, PastItsCapacityThePoolHandsOutOrdinaryBuffers) {
  MatPool pool(8, 8, CV_8U, 2);
  std::vector<cv::Mat> held;
  for (int k = 0; k < 5; ++k) held.push_back(pool.Take());
  EXPECT_EQ(pool.pooled(), 2u);
  EXPECT_TRUE(pool.Owns(held[0]));
  EXPECT_TRUE(pool.Owns(held[1]));
  EXPECT_FALSE(pool.Owns(held[4]));
  for (const cv::Mat& m : held) EXPECT_EQ(m.total(), 64u);
  held.clear();  // The unpooled ones go back to the heap, the pooled ones to the pool.
  EXPECT_EQ(pool.in_use(), 0u);
  cv::Mat again = pool.Take();
  EXPECT_TRUE(pool.Owns(again));
}

TEST(MatPoolTest, TakeZerosClearsAReusedBuffer) {
  MatPool pool(16, 16, CV_32F, 1);
  cv::Mat a = pool.Take();
  a.setTo(7.0f);
  a.release();
  cv::Mat b = pool.TakeZeros();
  EXPECT_EQ(cv::countNonZero(b), 0);
}

// Holders on other threads let go while the owner takes: no buffer is ever handed out twice
// (each taker writes its own mark and finds it intact).
TEST(MatPoolTest, BuffersReleasedOnOtherThreadsAreNeverHandedOutTwice) {
  MatPool pool(32, 32, CV_32S, 16);
  std::vector<std::thread> threads;
  std::atomic<int> clobbered{0};
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&pool, &clobbered, t] {
      for (int k = 0; k < 2000; ++k) {
        cv::Mat m = pool.Take();
        const int mark = t * 100000 + k;
        m.setTo(mark);
        std::this_thread::yield();
        if (m.at<int>(0, 0) != mark || m.at<int>(31, 31) != mark) ++clobbered;
      }
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(clobbered.load(), 0);
  EXPECT_LE(pool.pooled(), 16u);
  EXPECT_EQ(pool.in_use(), 0u);
}

}  // namespace
}  // namespace irmosaic
