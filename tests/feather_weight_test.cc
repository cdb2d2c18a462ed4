// Seam-blending weights of undistorted frames (src/feather_weight.h): the vector paths over each
// row's span against the scalar reference over whole rows, and the reference against the
// distance it stands for.
#include "../src/feather_weight.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <opencv2/imgproc.hpp>
#include <random>

#include "../src/simd_dispatch.h"

namespace irmosaic {
namespace {

// The footprint mask as the orthorectifier fills it (sub-pixel vertices, 4 fractional bits).
cv::Mat FilledMask(cv::Size size, const std::array<Eigen::Vector2d, 4>& quad) {
  cv::Mat mask(size, CV_8U, cv::Scalar(0));
  constexpr int kShift = 4;
  std::array<cv::Point, 4> points;
  for (int k = 0; k < 4; ++k) {
    points[k] = cv::Point(static_cast<int>(std::lround(quad[k].x() * (1 << kShift))),
                          static_cast<int>(std::lround(quad[k].y() * (1 << kShift))));
  }
  cv::fillConvexPoly(mask, points.data(), 4, cv::Scalar(255), cv::LINE_8, kShift);
  return mask;
}

// A 640 x 512 frame's outline under a random oblique, rotated, scaled view, shifted so that it
// lies in, across or beside a w x h image; either orientation.
std::array<Eigen::Vector2d, 4> RandomQuad(std::mt19937* rng, int w, int h) {
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double angle = unit(*rng) * 2.0 * M_PI, scale = 0.3 + 1.5 * unit(*rng);
  const double tilt = (unit(*rng) - 0.5) * 0.003;  // Perspective: near edge short, far edge long.
  Eigen::Matrix3d m;
  m << scale * std::cos(angle), -scale * std::sin(angle), 0.0, scale * std::sin(angle),
      scale * std::cos(angle), 0.0, tilt * std::cos(angle), tilt * std::sin(angle), 1.0;
  const std::array<Eigen::Vector2d, 4> corners = {
      Eigen::Vector2d(-320.5, -256.5), Eigen::Vector2d(319.5, -256.5),
      Eigen::Vector2d(319.5, 255.5), Eigen::Vector2d(-320.5, 255.5)};
  // One draw a statement, y first: a call's argument order is unspecified.
  const double centre_y = (unit(*rng) * 1.4 - 0.2) * h;
  const Eigen::Vector2d centre((unit(*rng) * 1.4 - 0.2) * w, centre_y);
  std::array<Eigen::Vector2d, 4> quad;
  for (int k = 0; k < 4; ++k) {
    const Eigen::Vector3d p = m * corners[k].homogeneous();
    quad[k] = p.hnormalized() + centre;
  }
  if (unit(*rng) < 0.5) std::swap(quad[1], quad[3]);  // The other orientation.
  return quad;
}

TEST(FeatherWeightTest, VectorPathsOverEachRowsSpanEqualTheScalarReference) {
  std::mt19937 rng(11);
  std::uniform_int_distribution<int> side(1, 900);
  int compared = 0, positive = 0;
  for (int trial = 0; trial < 300; ++trial) {
    const int height = side(rng) * 3 / 4 + 1;  // Drawn first (the same sizes for every compiler).
    const cv::Size size(side(rng), height);
    const std::array<Eigen::Vector2d, 4> quad = RandomQuad(&rng, size.width, size.height);
    cv::Mat mask = FilledMask(size, quad);
    if (trial % 3 == 0) {
      // A clip (FrameGeometry::image_clip) or anything else may unset mask pixels.
      cv::Mat holes(size, CV_8U);
      cv::randu(holes, 0, 4);
      mask.setTo(0, holes == 0);
    }
    const double feather = trial % 5 == 0 ? 1.0 : 24.0;
    cv::Mat reference, fast, baseline;
    feather::WeightScalar(quad, feather, mask, &reference);
    feather::Weight(quad, feather, mask, &fast);  // AVX2 where the CPU has it.
    const bool before = simd::SetAvx2Allowed(false);
    feather::Weight(quad, feather, mask, &baseline);  // SSE2.
    simd::SetAvx2Allowed(before);
    ASSERT_EQ(cv::norm(fast, reference, cv::NORM_INF), 0.0) << "trial " << trial;
    ASSERT_EQ(cv::norm(baseline, reference, cv::NORM_INF), 0.0) << "trial " << trial;
    compared += static_cast<int>(size.area());
    positive += cv::countNonZero(reference > 0.0f);
  }
  // Most quads cover part of their image, and the weights inside are not all cut to zero.
  EXPECT_GT(positive, compared / 10);
}

// The reference is the distance it stands for: for an axis-aligned rectangle of whole pixels,
// (distance to the outer pixel edge + 0.5) is cv::distanceTransform's exact Euclidean distance
// to the nearest pixel outside (its centre).
TEST(FeatherWeightTest, WeightsOfARectangleFollowTheDistanceToItsBorder) {
  const cv::Size size(300, 200);
  const cv::Rect rect(37, 21, 211, 150);
  const std::array<Eigen::Vector2d, 4> quad = {
      Eigen::Vector2d(rect.x - 0.5, rect.y - 0.5),
      Eigen::Vector2d(rect.x + rect.width - 0.5, rect.y - 0.5),
      Eigen::Vector2d(rect.x + rect.width - 0.5, rect.y + rect.height - 0.5),
      Eigen::Vector2d(rect.x - 0.5, rect.y + rect.height - 0.5)};
  cv::Mat mask(size, CV_8U, cv::Scalar(0));
  mask(rect).setTo(255);
  constexpr double kFeather = 24.0;
  cv::Mat weight, distance;
  feather::Weight(quad, kFeather, mask, &weight);
  cv::distanceTransform(mask, distance, cv::DIST_L2, cv::DIST_MASK_PRECISE, CV_32F);
  cv::Mat expected;
  distance.convertTo(expected, CV_32F, 1.0 / kFeather);
  cv::min(expected, 1.0, expected);
  EXPECT_LT(cv::norm(weight, expected, cv::NORM_INF), 1e-5);
  // Spot values: the outermost pixel ring 1 / 24, the centre 1, outside 0.
  EXPECT_NEAR(weight.at<float>(rect.y + 75, rect.x), 1.0 / kFeather, 1e-6);
  EXPECT_NEAR(weight.at<float>(rect.y + 75, rect.x + 3), 4.0 / kFeather, 1e-6);
  EXPECT_EQ(weight.at<float>(rect.y + 75, rect.x + 100), 1.0f);
  EXPECT_EQ(weight.at<float>(rect.y + 75, rect.x - 1), 0.0f);
}

}  // namespace
}  // namespace irmosaic
