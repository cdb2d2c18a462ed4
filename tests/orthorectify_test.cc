// Orthorectification: a frame warped onto the mosaic plane with its validity mask.
#include "irmosaic/orthorectify.h"

#include <gtest/gtest.h>

#include <opencv2/imgproc.hpp>
#include <random>

#include "../src/simd_dispatch.h"
#include "../src/warp_bilinear.h"
#include "irmosaic/error.h"
#include "irmosaic/frame_geometry.h"

namespace irmosaic {
namespace {

// A smooth 16-bit test pattern: bilinear resampling reproduces it to well under 1 DN.
cv::Mat SmoothPattern(int width, int height) {
  cv::Mat image(height, width, CV_16U);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x)
      image.at<uint16_t>(y, x) =
          static_cast<uint16_t>(20000 + 8000 * std::sin(x * 0.05) * std::cos(y * 0.037) + 10.0 * x);
  return image;
}

// Bilinear sample of a one-channel image at a sub-pixel position.
double Bilinear(const cv::Mat& image, double x, double y) {
  cv::Mat f;
  image.convertTo(f, CV_32F);
  cv::Mat sample;
  cv::getRectSubPix(f, {1, 1}, cv::Point2f(static_cast<float>(x), static_cast<float>(y)), sample);
  return sample.at<float>(0);
}

Eigen::Matrix3d ObliqueHomography(const CameraModel& camera, double sweep_deg = -35.0) {
  PosRecord r;
  r.lat_deg = 47.2;
  r.lon_deg = 8.5;
  r.height_m = 1000.0;
  r.yaw_deg = 33.0;
  r.gimbal_roll_deg = sweep_deg;
  const FrameGeometry g = ComputeFrameGeometry(camera, PoseFromRecord(r), LocalFrame(47.2, 8.5),
                                               MosaicGrid{0.5}, FlatGround(0.0));
  EXPECT_TRUE(g.ok) << g.problem;
  return g.mosaic_from_image;
}

// A linear ramp (bilinear interpolation is exact on it), so a value error converts to a
// position error: error_px = error_dn / |gradient|.
cv::Mat Ramp(int width, int height, double gx, double gy) {
  cv::Mat image(height, width, CV_16U);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x)
      image.at<uint16_t>(y, x) = static_cast<uint16_t>(std::lround(1000 + gx * x + gy * y));
  return image;
}

// Oblique frames take warpPerspective; near-nadir ones the affine shortcut (within 0.01 px).
class OrthorectifyPlacement : public ::testing::TestWithParam<double> {};

TEST_P(OrthorectifyPlacement, PixelsLandWhereTheHomographySaysWithin0p05px) {
  const CameraModel camera = DefaultInfraredCamera();
  const double gx = 40.0, gy = 27.0;
  const cv::Mat frame = Ramp(camera.width, camera.height, gx, gy);
  const Eigen::Matrix3d h = ObliqueHomography(camera, GetParam());
  const OrthoImage ortho = Orthorectify(frame, camera, h);
  ASSERT_FALSE(ortho.empty());
  EXPECT_EQ(ortho.image.type(), CV_16U);
  double worst_dn = 0.0;
  int checked = 0;
  for (int y = 20; y < camera.height - 20; y += 37) {
    for (int x = 20; x < camera.width - 20; x += 41) {
      // Integer ortho pixel near the frame pixel's image; compare with the frame sampled back.
      const Eigen::Vector2d o = ApplyHomography(ortho.ortho_from_image, {x, y});
      const cv::Point op(static_cast<int>(std::lround(o.x())),
                         static_cast<int>(std::lround(o.y())));
      ASSERT_EQ(ortho.mask.at<uint8_t>(op), 255);
      const Eigen::Vector2d back = ApplyHomography(ortho.ortho_from_image.inverse(), {op.x, op.y});
      worst_dn = std::max(
          worst_dn, std::abs(Bilinear(frame, back.x(), back.y()) - ortho.image.at<uint16_t>(op)));
      ++checked;
    }
  }
  EXPECT_GT(checked, 100);
  // Position error in frame pixels (OpenCV warps at 1/32 px; 16-bit rounding adds 0.5 DN).
  EXPECT_LT(worst_dn / std::hypot(gx, gy), 0.05) << worst_dn << " DN";
}

INSTANTIATE_TEST_SUITE_P(SweepAngles, OrthorectifyPlacement, ::testing::Values(-35.0, 0.0));

TEST(OrthorectifyTest, MaskCoversExactlyTheFootprint) {
  const CameraModel camera = DefaultInfraredCamera();
  const cv::Mat frame(camera.height, camera.width, CV_8U, cv::Scalar(128));
  const Eigen::Matrix3d h = ObliqueHomography(camera);
  const OrthoImage ortho = Orthorectify(frame, camera, h);
  // Area of the footprint quadrilateral (in ortho pixels) vs. the mask's pixel count.
  std::vector<cv::Point2f> corners;
  for (const Eigen::Vector2d& c : {Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(639.5, -0.5),
                                   Eigen::Vector2d(639.5, 511.5), Eigen::Vector2d(-0.5, 511.5)}) {
    const Eigen::Vector2d o = ApplyHomography(ortho.ortho_from_image, c);
    corners.emplace_back(static_cast<float>(o.x()), static_cast<float>(o.y()));
  }
  const double area = cv::contourArea(corners);
  const double count = cv::countNonZero(ortho.mask);
  double perimeter = cv::arcLength(corners, true);
  EXPECT_NEAR(count, area, perimeter);  // Within one pixel along the border.
  // Inside the mask, the constant frame stays constant; outside, nothing claims data.
  cv::Mat values;
  ortho.image.copyTo(values, ortho.mask);
  double lo = 0, hi = 0;
  cv::minMaxLoc(ortho.image, &lo, &hi, nullptr, nullptr, ortho.mask);
  EXPECT_EQ(lo, 128);
  EXPECT_EQ(hi, 128);
}

TEST(OrthorectifyTest, DistortionIsUndoneInTheSameResampling) {
  CameraModel camera = DefaultInfraredCamera();
  camera.distortion = {-0.2, 0.05, 0.0, 0.0, 0.0};
  const cv::Mat frame = SmoothPattern(camera.width, camera.height);
  const Eigen::Matrix3d h = ObliqueHomography(camera);
  const OrthoImage ortho = Orthorectify(frame, camera, h);
  double worst_dn = 0.0;
  for (int y = 30; y < camera.height - 30; y += 53) {
    for (int x = 30; x < camera.width - 30; x += 59) {
      // Recorded pixel -> undistorted -> ortho: the ortho value equals the recorded value.
      const Eigen::Vector2d u = camera.Undistort({x, y});
      const Eigen::Vector2d o = ApplyHomography(ortho.ortho_from_image, u);
      worst_dn = std::max(worst_dn,
                          std::abs(Bilinear(ortho.image, o.x(), o.y()) - frame.at<uint16_t>(y, x)));
    }
  }
  EXPECT_LT(worst_dn, 8.0);  // Two bilinear resamplings of a pattern of <= 400 DN/px.
}

// With reused output buffers: the same pixels as fresh buffers, with and without distortion,
// as the orthoimage's size changes; once the largest size has been seen, no new buffer.
TEST(OrthorectifyTest, ReusedOutputBuffersGiveTheSameOrthoimages) {
  for (const bool distorted : {false, true}) {
    CameraModel camera = DefaultInfraredCamera();
    if (distorted) camera.distortion = {-0.2, 0.05, 0.0, 0.0, 0.0};
    const cv::Mat frame = SmoothPattern(camera.width, camera.height);
    Orthorectifier fresh(camera), reused(camera);
    reused.set_reuse_output(true);
    const uchar* largest_buffer = nullptr;
    // The nadir frame's orthoimage is the smallest, 35 degrees off nadir the largest.
    for (const double sweep : {-20.0, 0.0, -35.0, 0.0, -20.0, -35.0}) {
      const Eigen::Matrix3d h = ObliqueHomography(camera, sweep);
      OrthoImage a, b;
      fresh.Run(frame, h, &a);
      reused.Run(frame, h, &b);
      ASSERT_EQ(a.image.size(), b.image.size()) << "sweep " << sweep;
      EXPECT_EQ(a.origin_px, b.origin_px);
      EXPECT_EQ(cv::norm(a.image, b.image, cv::NORM_INF), 0.0) << "sweep " << sweep;
      EXPECT_EQ(cv::norm(a.mask, b.mask, cv::NORM_INF), 0.0) << "sweep " << sweep;
      if (sweep == -35.0) {
        if (largest_buffer) {
          EXPECT_EQ(b.image.data, largest_buffer) << "distorted " << distorted;
        }
        largest_buffer = b.image.data;
      }
    }
  }
}

// Footprint only (the renderer's setting): the same mask, and under it the same pixels as the
// whole-box warp up to OpenCV's resampling grain: each band's map starts at the band's corner,
// so a coordinate may round to the neighbouring step of OpenCV's 1/32 px interpolation table
// (the affine shortcut rounds its fixed-point start per band; at most 400 / 32 = 12.5 DN on this
// pattern of <= 400 DN per pixel). Outside the footprint's bands nothing is resampled: under
// 60 % of the box 35 degrees off nadir, where the whole-box warp resamples all of it.
TEST(OrthorectifyTest, FootprintOnlyWarpsTheFootprintAndMatchesTheWholeBox) {
  const CameraModel camera = DefaultInfraredCamera();
  const cv::Mat frame = SmoothPattern(camera.width, camera.height);
  OrthoOptions footprint_only;
  footprint_only.footprint_only = true;
  Orthorectifier whole(camera), part(camera, footprint_only);
  part.set_reuse_output(true);  // As the renderer runs it: stale values must not survive.
  // Oblique (warpPerspective) and nadir (the affine shortcut), twice so reused buffers are hit.
  for (const double sweep : {-35.0, 0.0, -20.0, -35.0}) {
    const Eigen::Matrix3d h = ObliqueHomography(camera, sweep);
    OrthoImage a, b;
    whole.Run(frame, h, &a);
    part.Run(frame, h, &b);
    ASSERT_EQ(a.image.size(), b.image.size());
    EXPECT_EQ(a.origin_px, b.origin_px);
    EXPECT_EQ(cv::norm(a.mask, b.mask, cv::NORM_INF), 0.0) << "sweep " << sweep;
    cv::Mat diff, differs;
    cv::absdiff(a.image, b.image, diff);
    EXPECT_LE(cv::norm(diff, cv::NORM_INF, a.mask), 13.0) << "sweep " << sweep;
    cv::compare(diff, 0, differs, cv::CMP_GT);
    cv::bitwise_and(differs, a.mask, differs);
    EXPECT_LT(cv::countNonZero(differs), cv::countNonZero(a.mask) / 20) << "sweep " << sweep;
    // Resampled samples (the pattern is >= 10000 DN) hold the whole-box values there too.
    const cv::Mat resampled = b.image != 0;
    EXPECT_LE(cv::norm(diff, cv::NORM_INF, resampled), 13.0) << "sweep " << sweep;
    if (sweep == -35.0) {
      EXPECT_LT(cv::countNonZero(resampled), 0.6 * b.image.total());
    }
  }
}

// The own 16-bit warp (OrthoOptions::exact_bilinear_16bit) computes positions in float instead
// of OpenCV's 1/32 px: on a ramp its values are the exact bilinear ones but for the rounding to
// 16 bits (0.5 DN, 0.0104 px at this gradient), over the whole box and over the footprint.
TEST(OrthorectifyTest, ExactBilinearWarpPlacesPixelsWithinTheRoundingOf16Bits) {
  const CameraModel camera = DefaultInfraredCamera();
  const double gx = 40.0, gy = 27.0;
  const cv::Mat frame = Ramp(camera.width, camera.height, gx, gy);
  for (const bool footprint_only : {false, true}) {
    OrthoOptions options;
    options.exact_bilinear_16bit = true;
    options.footprint_only = footprint_only;
    for (const double sweep : {-35.0, 0.0}) {
      const OrthoImage ortho =
          Orthorectify(frame, camera, ObliqueHomography(camera, sweep), options);
      ASSERT_EQ(ortho.image.type(), CV_16U);
      double worst_dn = 0.0;
      int checked = 0;
      const Eigen::Matrix3d image_from_ortho = ortho.ortho_from_image.inverse();
      for (int y = 0; y < ortho.image.rows; y += 7) {
        for (int x = 0; x < ortho.image.cols; x += 5) {
          if (ortho.mask.at<uint8_t>(y, x) == 0) continue;
          const Eigen::Vector2d back = ApplyHomography(image_from_ortho, {x, y});
          // Inside the frame by a pixel (the border replicates, the ramp does not).
          if (back.x() < 0 || back.y() < 0 || back.x() > camera.width - 1 ||
              back.y() > camera.height - 1) {
            continue;
          }
          const double expected = 1000 + gx * back.x() + gy * back.y();
          worst_dn = std::max(worst_dn, std::abs(expected - ortho.image.at<uint16_t>(y, x)));
          ++checked;
        }
      }
      EXPECT_GT(checked, 1000);
      // 0.5 DN of rounding, and the ramp's own rounding to integers at the samples (0.5 DN).
      EXPECT_LT(worst_dn / std::hypot(gx, gy), 0.025)
          << worst_dn << " DN, sweep " << sweep << ", footprint only " << footprint_only;
    }
  }
}

// The own warp's AVX2 path (8 pixels at a time, chosen at run time) gives the very values of its
// scalar path, for 16-bit and 8-bit frames: row lengths 1-37 (every tail), projective and affine
// maps, positions far outside the frame (replicated border: the last row's last pixels, where
// the 8-bit gathers read the buffer's last bytes) and behind the camera (clamped, no crash),
// with the gather instruction and with the eight loads that stand in for it.
TEST(OrthorectifyTest, ExactBilinearWarpAvx2AndScalarPathsAgreeBitForBit) {
  if (!simd::Avx2()) GTEST_SKIP() << "this CPU has no AVX2: only the scalar path runs";
  const CameraModel camera = DefaultInfraredCamera();
  std::vector<cv::Matx33d> maps;
  for (const double sweep : {-35.0, -10.0, 0.0}) {
    const Eigen::Matrix3d h = ObliqueHomography(camera, sweep).inverse();
    cv::Matx33d m;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) m(r, c) = h(r, c) / h(2, 2);
    maps.push_back(m * cv::Matx33d(1, 0, -2000, 0, 1, -1500, 0, 0, 1));
  }
  maps.push_back(cv::Matx33d(0.93, 0.21, 17.25, -0.17, 1.07, -3.5, 0, 0, 1));
  maps.push_back(cv::Matx33d(1.5, 0.0, -100.0, 0.0, 1.5, -90.0, 0.001, 0.0004, 0.2));
  maps.push_back(cv::Matx33d(1, 0, 0, 0, 1, 0, -0.01, 0, 1));  // W crosses 0 at x = 100.
  for (const int depth : {CV_16U, CV_8U}) {
    std::mt19937 rng(5);
    // A buffer of exactly the frame's bytes, so a read past its end is out of the allocation
    // (ASan's build reports it).
    cv::Mat src(512, 640, depth);
    cv::randu(src, 0, depth == CV_16U ? 65536 : 256);
    std::uniform_int_distribution<int> offset(0, 700);
    int compared = 0;
    for (const cv::Matx33d& m : maps) {
      for (int width = 1; width <= 37; ++width) {
        // One draw a statement, y first: a call's argument order is unspecified.
        const double shift_y = offset(rng) * 0.7;
        const cv::Matx33d shift(1, 0, offset(rng), 0, 1, shift_y, 0, 0, 1);
        cv::Mat fast(3, width, depth), scalar(3, width, depth);
        ASSERT_TRUE(warp::WarpBilinear(src, m * shift, &fast));
        ASSERT_TRUE(warp::WarpBilinearScalar(src, m * shift, &scalar));
        ASSERT_EQ(cv::norm(fast, scalar, cv::NORM_INF), 0.0) << "width " << width;
        // Both ways of reading the pixel pairs, whichever this machine chose.
        for (const warp::GatherPath gather :
             {warp::GatherPath::kHardware, warp::GatherPath::kEmulated}) {
          cv::Mat path(3, width, depth, cv::Scalar(1));
          ASSERT_TRUE(warp::WarpBilinearAvx2(src, m * shift, &path, gather));
          ASSERT_EQ(cv::norm(path, scalar, cv::NORM_INF), 0.0)
              << "width " << width << ", gather " << static_cast<int>(gather);
        }
        compared += width * 3;
      }
    }
    EXPECT_EQ(compared, 6 * 3 * 37 * 38 / 2);
  }
  // Not its business: other types, mixed types and tiny frames go to OpenCV.
  cv::Mat out(4, 4, CV_16U);
  EXPECT_FALSE(warp::WarpBilinear(cv::Mat(4, 4, CV_32F, cv::Scalar(1)), maps[3], &out));
  EXPECT_FALSE(warp::WarpBilinear(cv::Mat(4, 4, CV_8U, cv::Scalar(1)), maps[3], &out));
  EXPECT_FALSE(warp::WarpBilinear(cv::Mat(1, 4, CV_16U, cv::Scalar(1)), maps[3], &out));
  EXPECT_FALSE(warp::WarpBilinearAvx2(cv::Mat(4, 4, CV_32F, cv::Scalar(1)), maps[3], &out,
                                      warp::GatherPath::kEmulated));
  const std::string chosen = warp::GatherPathName();
  EXPECT_TRUE(chosen == "hardware" || chosen == "emulated") << chosen;
}

// 8-bit frames go through the same warp as 16-bit ones: the same samples held in either type
// warp to the same values (so the 16-bit ramp test above bounds the 8-bit warp too), through
// Orthorectify's whole box and footprint paths, oblique and nadir (the affine branch is
// OpenCV's only when the own warp is off).
TEST(OrthorectifyTest, ExactBilinearWarpOf8BitFramesEqualsItsWarpOf16Bit) {
  const CameraModel camera = DefaultInfraredCamera();
  cv::Mat frame8(camera.height, camera.width, CV_8U), frame16;
  cv::randu(frame8, 0, 256);
  cv::GaussianBlur(frame8, frame8, cv::Size(0, 0), 1.5);
  frame8.convertTo(frame16, CV_16U);
  for (const bool footprint_only : {false, true}) {
    OrthoOptions options;
    options.footprint_only = footprint_only;
    for (const double sweep : {-35.0, 0.0}) {
      const Eigen::Matrix3d h = ObliqueHomography(camera, sweep);
      const OrthoImage a = Orthorectify(frame8, camera, h, options);
      const OrthoImage b = Orthorectify(frame16, camera, h, options);
      ASSERT_EQ(a.image.type(), CV_8U);
      cv::Mat a16;
      a.image.convertTo(a16, CV_16U);
      EXPECT_EQ(cv::norm(a16, b.image, cv::NORM_INF), 0.0)
          << "sweep " << sweep << ", footprint only " << footprint_only;
      EXPECT_EQ(cv::norm(a.mask, b.mask, cv::NORM_INF), 0.0);
    }
  }
}

TEST(OrthorectifyTest, BadFramesAreRefused) {
  const CameraModel camera = DefaultInfraredCamera();
  const Eigen::Matrix3d h = ObliqueHomography(camera);
  EXPECT_THROW(Orthorectify(cv::Mat(), camera, h), InputError);
  EXPECT_THROW(Orthorectify(cv::Mat(512, 640, CV_8UC3), camera, h), InputError);
  Eigen::Matrix3d nan_h = h;
  nan_h(0, 0) = std::nan("");
  EXPECT_THROW(Orthorectify(cv::Mat(512, 640, CV_8U), camera, nan_h), InputError);
  // An absurdly fine grid: the orthoimage would be enormous.
  Eigen::Matrix3d zoom = Eigen::Matrix3d::Identity();
  zoom(0, 0) = zoom(1, 1) = 50.0;
  EXPECT_THROW(Orthorectify(cv::Mat(512, 640, CV_8U), camera, zoom * h,
                            OrthoOptions{cv::INTER_LINEAR, 8192}),
               InputError);
}

}  // namespace
}  // namespace irmosaic
