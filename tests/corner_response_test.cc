// The key-point detector's corner response (src/corner_response.h) against OpenCV's
// cv::cornerMinEigenVal, whose definition it computes in one pass.
#include "../src/corner_response.h"

#include <gtest/gtest.h>

#include <opencv2/imgproc.hpp>
#include <random>

#include "irmosaic/keypoints.h"

namespace irmosaic {
namespace {

// A textured float image: smoothed noise (corners and edges of every strength) on a ramp, with
// values in the range of 16-bit thermal counts.
cv::Mat Textured(cv::Size size, uint32_t seed) {
  cv::Mat noise(size, CV_32F);
  cv::RNG rng(seed);
  rng.fill(noise, cv::RNG::UNIFORM, 0.0, 4000.0);
  cv::Mat image;
  cv::GaussianBlur(noise, image, cv::Size(), 1.5);
  for (int y = 0; y < image.rows; ++y) {
    for (int x = 0; x < image.cols; ++x) image.at<float>(y, x) += 20.0f * x + 7.0f * y + 20000.0f;
  }
  return image;
}

// Largest difference from OpenCV's response, relative to OpenCV's largest response.
double RelativeDifference(const cv::Mat& image, int block) {
  cv::Mat ours, theirs;
  corner::MinEigenResponse(image, block, &ours);
  cv::cornerMinEigenVal(image, theirs, block, 3);
  EXPECT_EQ(ours.size(), theirs.size());
  EXPECT_EQ(ours.type(), CV_32F);
  double peak = 0.0, diff = 0.0;
  cv::minMaxLoc(cv::abs(theirs), nullptr, &peak);
  cv::minMaxLoc(cv::abs(ours - theirs), nullptr, &diff);
  return diff / std::max(peak, 1e-30);
}

TEST(CornerResponseTest, EqualsOpenCvsMinEigenValueOverTheWholeImageBordersIncluded) {
  uint32_t seed = 1;
  double worst = 0.0;
  for (const cv::Size size : {cv::Size(330, 270), cv::Size(641, 513), cv::Size(37, 12),
                              cv::Size(12, 37), cv::Size(9, 9), cv::Size(101, 7)}) {
    for (const int block : {3, 5, 9, 15}) {
      const double relative = RelativeDifference(Textured(size, seed++), block);
      // Both compute (a + c) - sqrt((a - c)^2 + b^2) in float, which cancels where the smaller
      // eigenvalue is far below the larger: the sums' rounding (~1e-7 relative, OpenCV's box
      // filter sums in double) comes out as up to ~1e-5 of the peak (measured: 2.2e-6 to 1.04e-5).
      EXPECT_LT(relative, 3e-5) << size << " block " << block;
      worst = std::max(worst, relative);
    }
  }
  std::printf("largest difference from cv::cornerMinEigenVal: %.3g of its peak response\n", worst);
}

TEST(CornerResponseTest, FlatAndRampImagesGiveZeroWhereOpenCvDoes) {
  cv::Mat flat(40, 50, CV_32F, cv::Scalar(1234.0f));
  cv::Mat ours;
  corner::MinEigenResponse(flat, 5, &ours);
  double lo = 0.0, hi = 0.0;
  cv::minMaxLoc(ours, &lo, &hi);
  EXPECT_EQ(lo, 0.0);
  EXPECT_EQ(hi, 0.0);
  // A ramp is an edge everywhere, a corner nowhere: the smaller eigenvalue is ~0 inside (the
  // borders' reflection makes corners there, as in OpenCV's).
  cv::Mat ramp(40, 50, CV_32F);
  for (int y = 0; y < ramp.rows; ++y) {
    for (int x = 0; x < ramp.cols; ++x) ramp.at<float>(y, x) = 3.0f * x;
  }
  corner::MinEigenResponse(ramp, 5, &ours);
  cv::minMaxLoc(ours(cv::Rect(4, 4, 42, 32)), &lo, &hi);
  EXPECT_LT(std::max(std::abs(lo), std::abs(hi)), 1e-3);
  EXPECT_LT(RelativeDifference(ramp, 5), 3e-5);
}

// A window of a larger image is read on its own (borders reflected inside the window), as a
// copy of it would be.
TEST(CornerResponseTest, AWindowIsReadAsACopyOfIt) {
  const cv::Mat image = Textured(cv::Size(200, 150), 99);
  const cv::Rect window(30, 20, 100, 80);
  cv::Mat in_place, copied;
  corner::MinEigenResponse(image(window), 5, &in_place);
  corner::MinEigenResponse(image(window).clone(), 5, &copied);
  EXPECT_EQ(cv::norm(in_place, copied, cv::NORM_INF), 0.0);
}

// The detector with it picks the same key points as with OpenCV's response on textured images
// (cell maxima of responses that agree to ~1e-7 relative; a tie that close would be a coin
// toss either way).
TEST(CornerResponseTest, DetectorPicksTheKeyPointsOfOpenCvsResponse) {
  int same = 0, total = 0;
  for (uint32_t seed = 1; seed <= 20; ++seed) {
    const cv::Mat image = Textured(cv::Size(320, 256), 1000 + seed);
    cv::Mat valid(image.size(), CV_8U, cv::Scalar(0));
    valid(cv::Rect(20, 16, 280, 224)).setTo(255);
    KeypointOptions options;
    options.presmooth_sigma_px = 0.866;
    options.block_size = 5;
    options.min_distance_px = 5.0;
    const std::vector<Eigen::Vector2d> points = DetectKeypoints(image, valid, options);
    // The same selection, from OpenCV's response.
    const cv::Rect box = cv::boundingRect(valid);
    const int margin = options.block_size + static_cast<int>(3 * options.presmooth_sigma_px) + 1;
    const cv::Rect outer = (box + cv::Size(2 * margin, 2 * margin) - cv::Point(margin, margin)) &
                           cv::Rect(0, 0, image.cols, image.rows);
    cv::Mat region = image(outer).clone(), response;
    cv::GaussianBlur(region, region, cv::Size(), options.presmooth_sigma_px);
    cv::cornerMinEigenVal(region, response, options.block_size, 3);
    for (const Eigen::Vector2d& p : points) {
      const cv::Point at(static_cast<int>(p.x()), static_cast<int>(p.y()));
      // The point is its cell's maximum of OpenCV's response too.
      const int gx = (at.x - box.x) * options.grid_cols / box.width;
      const int gy = (at.y - box.y) * options.grid_rows / box.height;
      const cv::Rect cell(
          box.x + box.width * gx / options.grid_cols, box.y + box.height * gy / options.grid_rows,
          box.width * (gx + 1) / options.grid_cols - box.width * gx / options.grid_cols,
          box.height * (gy + 1) / options.grid_rows - box.height * gy / options.grid_rows);
      cv::Point best;
      cv::minMaxLoc(response(cell - outer.tl()), nullptr, nullptr, nullptr, &best);
      same += best + cell.tl() == at;
      ++total;
    }
  }
  std::printf("%d of %d key points are their cell's maximum of OpenCV's response\n", same, total);
  EXPECT_GE(total, 20 * 40);
  EXPECT_EQ(same, total);
}

}  // namespace
}  // namespace irmosaic
