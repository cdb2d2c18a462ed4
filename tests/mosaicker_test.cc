// The whole pipeline as a library object on a simulated flight: radiometric compensation of
// automatic-gain-control jumps, and bad frames skipped with reasons.
#include "irmosaic/mosaicker.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <opencv2/imgproc.hpp>

#include "irmosaic/frame_geometry.h"
#include "irmosaic/orthorectify.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

namespace irmosaic {
namespace {
namespace fs = std::filesystem;

SynthOptions Flight(int frames) {
  SynthOptions options;
  options.ground_path = testing::SamplePath("sample_flight/ground_naip_2019.tif");
  options.seed = 11;
  options.frame_count = frames;
  options.altitude_m = 600;
  options.heading_deg = 80;
  options.frames_per_sweep = 8;
  options.sensor.noise_psnr_db = 35.0;
  return options;
}

// Mean absolute difference between frames i and j over their overlap on the mosaic, each
// frame rendered with its placement and (gain, offset), as a fraction of the value range.
double OverlapDifference(const FlightSimulator& sim, const std::vector<FramePlacement>& placed,
                         const std::vector<cv::Mat>& images, int i, int j, bool compensated,
                         double range) {
  const OrthoImage a = Orthorectify(images[i], sim.camera(), placed[i].mosaic_from_image);
  const OrthoImage b = Orthorectify(images[j], sim.camera(), placed[j].mosaic_from_image);
  const cv::Rect ra(a.origin_px, a.image.size()), rb(b.origin_px, b.image.size());
  const cv::Rect common = ra & rb;
  if (common.area() == 0) return -1.0;
  cv::Mat va, vb;
  a.image(common - a.origin_px)
      .convertTo(va, CV_32F, compensated ? placed[i].gain : 1.0,
                 compensated ? placed[i].offset : 0.0);
  b.image(common - b.origin_px)
      .convertTo(vb, CV_32F, compensated ? placed[j].gain : 1.0,
                 compensated ? placed[j].offset : 0.0);
  cv::Mat both = a.mask(common - a.origin_px) & b.mask(common - b.origin_px);
  cv::erode(both, both, cv::Mat(), cv::Point(-1, -1), 3);
  if (cv::countNonZero(both) < 500) return -1.0;
  // Blur away the sensor noise so the figure measures the radiometric mismatch.
  cv::GaussianBlur(va, va, cv::Size(0, 0), 3.0);
  cv::GaussianBlur(vb, vb, cv::Size(0, 0), 3.0);
  cv::Mat diff;
  cv::absdiff(va, vb, diff);
  return cv::mean(diff, both)[0] / range;
}

TEST(MosaickerTest, GainJumpsAreCompensatedAcrossOverlaps) {
  SynthOptions options = Flight(48);
  options.sensor.agc_gain_jump_fraction = 0.2;  // Gain levels uniform in 1 +- 20 %.
  options.sensor.agc_period_s = 0.12;           // A new level every 3 frames.
  options.sensor.vignetting = false;            // A separate effect (not compensated).
  FlightSimulator sim(options);
  const std::string store =
      (fs::temp_directory_path() / ("irmosaic_gain_" + std::to_string(::getpid()))).string();
  MosaickerOptions mo;
  mo.store_path = store;
  mo.mode = TileStoreOptions::Mode::kOverwrite;
  Mosaicker mosaicker(mo, sim.camera(), sim.MeasuredPos());
  std::vector<cv::Mat> images;
  for (int i = 0; i < sim.frame_count(); ++i) {
    SimFrame f = sim.Render(i);
    images.push_back(f.image);
    ASSERT_TRUE(mosaicker.Push(i, f.time_s, f.image).placed());
  }
  mosaicker.Finish();
  const std::vector<FramePlacement> placed = mosaicker.Placements();
  // The value range of the flight: 1st to 99th percentile of a frame.
  cv::Mat sorted;
  images[0].reshape(1, 1).convertTo(sorted, CV_32F);
  cv::sort(sorted, sorted, cv::SORT_ASCENDING);
  const double range =
      sorted.at<float>(sorted.cols * 99 / 100) - sorted.at<float>(sorted.cols / 100);
  double before = 0.0, after = 0.0;
  int pairs = 0;
  for (int j = 1; j < sim.frame_count(); ++j) {
    if (j % 8 == 0) continue;  // Fly-back: the previous frame is on the other side.
    const double b = OverlapDifference(sim, placed, images, j - 1, j, false, range);
    const double a = OverlapDifference(sim, placed, images, j - 1, j, true, range);
    if (b < 0 || a < 0) continue;
    before += b;
    after += a;
    ++pairs;
  }
  before /= pairs;
  after /= pairs;
  std::printf("overlap difference over %d pairs: before %.2f %%, after %.2f %% of the range\n",
              pairs, 100 * before, 100 * after);
  EXPECT_GT(pairs, 30);
  EXPECT_LT(after, 0.02);
  EXPECT_LT(after, 0.5 * before);
  fs::remove_all(store);
}

TEST(MosaickerTest, BadFramesAreSkippedWithReasonsAndTheRunGoesOn) {
  FlightSimulator sim(Flight(6));
  const std::string store =
      (fs::temp_directory_path() / ("irmosaic_bad_" + std::to_string(::getpid()))).string();
  MosaickerOptions mo;
  mo.store_path = store;
  mo.mode = TileStoreOptions::Mode::kOverwrite;
  Mosaicker mosaicker(mo, sim.camera(), sim.MeasuredPos());
  const SimFrame f0 = sim.Render(0);
  EXPECT_TRUE(mosaicker.Push(0, f0.time_s, f0.image).placed());
  // Outside the POS time range.
  const PushResult late = mosaicker.Push(1, 1000.0, sim.Render(1).image);
  EXPECT_FALSE(late.placed());
  EXPECT_NE(late.reason.find("frame 1"), std::string::npos) << late.reason;
  EXPECT_NE(late.reason.find("after the last POS record"), std::string::npos) << late.reason;
  // Wrong size, wrong type, empty.
  const PushResult small = mosaicker.Push(2, sim.Render(2).time_s, cv::Mat(100, 100, CV_16U));
  EXPECT_FALSE(small.placed());
  EXPECT_NE(small.reason.find("camera file says 640x512"), std::string::npos) << small.reason;
  EXPECT_FALSE(mosaicker.Push(3, sim.Render(3).time_s, cv::Mat()).placed());
  const SimFrame f3 = sim.Render(3);
  cv::Mat eight;
  f3.image.convertTo(eight, CV_8U, 1.0 / 256);
  const PushResult depth = mosaicker.Push(3, f3.time_s, eight);
  EXPECT_FALSE(depth.placed());
  EXPECT_NE(depth.reason.find("bit depth"), std::string::npos) << depth.reason;
  // The run goes on.
  const SimFrame f4 = sim.Render(4);
  EXPECT_TRUE(mosaicker.Push(4, f4.time_s, f4.image).placed());
  mosaicker.Finish();
  EXPECT_EQ(mosaicker.summary().frames_placed, 2);
  EXPECT_EQ(mosaicker.summary().frames_skipped, 4);
  fs::remove_all(store);
}

}  // namespace
}  // namespace irmosaic
