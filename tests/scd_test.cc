// SCD coarse matching: exact recovery, invariance, low overlap under noise, bad input.
#include "irmosaic/scd.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <opencv2/core/eigen.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <string>
#include <vector>

#include "irmosaic/frame_geometry.h"
#include "irmosaic/lsm.h"
#include "irmosaic/pos.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

namespace irmosaic {
namespace {

cv::Mat LoadFloat(const std::string& relative) {
  const cv::Mat gray = cv::imread(testing::SharedDataPath(relative), cv::IMREAD_GRAYSCALE);
  EXPECT_FALSE(gray.empty()) << relative;
  cv::Mat f;
  gray.convertTo(f, CV_32F);
  return f;
}

// `image` moved by `shift` (dst(x) = src(x - shift)), Lanczos so the shift is clean.
cv::Mat Shifted(const cv::Mat& image, const Eigen::Vector2d& shift) {
  const cv::Mat m = (cv::Mat_<double>(2, 3) << 1, 0, shift.x(), 0, 1, shift.y());
  cv::Mat out;
  cv::warpAffine(image, out, m, image.size(), cv::INTER_LANCZOS4, cv::BORDER_REFLECT);
  return out;
}

struct Pair {
  cv::Mat base, base_mask, templ, templ_mask;
  Eigen::Vector2d truth;  // template p <-> base p + truth
};

// Base = `image` moved by base_shift, cropped to a; template = `image` moved by templ_shift,
// cropped to b. Template p is image point p + b.tl - templ_shift, base q is q + a.tl -
// base_shift, so the truth is b.tl - a.tl - templ_shift + base_shift.
Pair CropPair(const cv::Mat& image, const cv::Rect& a, const cv::Rect& b,
              const Eigen::Vector2d& base_shift, const Eigen::Vector2d& templ_shift) {
  Pair p;
  p.base = Shifted(image, base_shift)(a).clone();
  p.templ = Shifted(image, templ_shift)(b).clone();
  p.truth = Eigen::Vector2d(b.x - a.x, b.y - a.y) - templ_shift + base_shift;
  return p;
}

double Error(const ScdResult& r, const Eigen::Vector2d& truth) { return (r.offset - truth).norm(); }

TEST(ScdTest, RecoversIntegerShiftsExactly) {
  const cv::Mat image = LoadFloat("geotiff/UTM2GTIF.tiff");
  ScdMatcher matcher;
  const cv::Rect a(100, 120, 420, 360);
  for (const cv::Point d : {cv::Point(150, 90), cv::Point(-37, 200), cv::Point(170, -13)}) {
    const cv::Rect b = a + d;
    Pair p = CropPair(image, a, b, {0, 0}, {0, 0});
    const Eigen::Vector2d predicted = p.truth + Eigen::Vector2d(23.0, -31.0);
    const ScdResult r = matcher.Match(p.base, cv::Mat(), p.templ, cv::Mat(), predicted, 64.0);
    ASSERT_TRUE(r.ok()) << r.reason;
    std::printf("SCD integer shift (%d, %d): error %.3f px, score %.3f\n", d.x, d.y,
                Error(r, p.truth), r.score);
    EXPECT_LT(Error(r, p.truth), 0.1) << "shift " << d;
    EXPECT_GT(r.score, 0.5);  // Under-floor pixels count as overlap with no orientation.
    EXPECT_NEAR(r.overlap_px, (a & b).area(), 0.5);
    EXPECT_NEAR(r.overlap_fraction, (a & b).area() / double(b.area()), 1e-9);
  }
}

TEST(ScdTest, RecoversSubPixelShifts) {
  ScdMatcher matcher;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> frac(-0.5, 0.5);
  for (const char* file : {"geotiff/UTM2GTIF.tiff", "thermal/seq_1_60_30/1_60_30_0_00010.jpg"}) {
    const cv::Mat image = LoadFloat(file);
    double worst = 0.0;
    for (int trial = 0; trial < 8; ++trial) {
      const cv::Rect a(20, 20, 300, 240);
      const cv::Rect b = a + cv::Point(150 + trial * 7, 100 - trial * 9);
      // The template's shift drawn first: a call's arguments are evaluated in an unspecified
      // order, and every compiler must draw the same shifts.
      const Eigen::Vector2d templ_shift{frac(rng), frac(rng)};
      const Pair p = CropPair(image, a, b, {frac(rng), frac(rng)}, templ_shift);
      const ScdResult r = matcher.Match(p.base, cv::Mat(), p.templ, cv::Mat(),
                                        p.truth + Eigen::Vector2d(-40, 35), 64.0);
      ASSERT_TRUE(r.ok()) << file << ": " << r.reason;
      worst = std::max(worst, Error(r, p.truth));
    }
    std::printf("SCD sub-pixel, %s: worst error %.3f px of 8 shifts\n", file, worst);
    EXPECT_LT(worst, 0.1) << file;
  }
}

TEST(ScdTest, EightAndSixteenBitAgreeWithFloat) {
  const cv::Mat image = LoadFloat("thermal/seq_1_60_30/1_60_30_0_00020.jpg");
  const cv::Rect a(10, 10, 360, 300), b(200, 150, 360, 300);
  const Pair p = CropPair(image, a, b, {0, 0}, {0, 0});
  ScdMatcher matcher;
  const ScdResult r32 =
      matcher.Match(p.base, cv::Mat(), p.templ, cv::Mat(), p.truth + Eigen::Vector2d(9, 9), 32);
  cv::Mat base8, templ8, base16, templ16;
  p.base.convertTo(base8, CV_8U);
  p.templ.convertTo(templ8, CV_8U);
  p.base.convertTo(base16, CV_16U, 200.0);
  p.templ.convertTo(templ16, CV_16U, 200.0);
  const ScdResult r8 =
      matcher.Match(base8, cv::Mat(), templ8, cv::Mat(), p.truth + Eigen::Vector2d(9, 9), 32);
  const ScdResult r16 =
      matcher.Match(base16, cv::Mat(), templ16, cv::Mat(), p.truth + Eigen::Vector2d(9, 9), 32);
  ASSERT_TRUE(r32.ok() && r8.ok() && r16.ok()) << r32.reason << r8.reason << r16.reason;
  std::printf("SCD 8/16 bit: float error %.3f px, 8-bit change %.3f, 16-bit change %.3f px\n",
              Error(r32, p.truth), (r8.offset - r32.offset).norm(),
              (r16.offset - r32.offset).norm());
  EXPECT_LT(Error(r32, p.truth), 0.1);
  EXPECT_LT((r8.offset - r32.offset).norm(), 0.05);
  EXPECT_LT((r16.offset - r32.offset).norm(), 0.05);
}

// The coarse search's reduction sums integer images as integers and float images as floats:
// both sums are exact (at most 64 samples of 16 bits), so the same values given as 8-bit,
// 16-bit or float images must give the same result to the last bit, at every pyramid factor,
// with masks, over crops whose widths leave tails for the vector loops.
TEST(ScdTest, IntegerAndFloatImagesReduceIdentically) {
  const cv::Mat image = LoadFloat("thermal/seq_1_60_30/1_60_30_0_00020.jpg");
  const Pair p =
      CropPair(image, cv::Rect(10, 10, 363, 301), cv::Rect(197, 151, 358, 299), {0, 0}, {0, 0});
  cv::Mat base_mask(p.base.size(), CV_8U, cv::Scalar(255));
  cv::Mat templ_mask(p.templ.size(), CV_8U, cv::Scalar(255));
  cv::circle(base_mask, {40, 250}, 60, cv::Scalar(0), cv::FILLED);
  cv::rectangle(templ_mask, cv::Rect(301, 0, 57, 41), cv::Scalar(0), cv::FILLED);
  for (const int factor : {2, 4, 8}) {
    ScdOptions options;
    options.pyramid_factor = factor;
    options.refine_at_full_resolution = false;
    ScdMatcher matcher(options);
    for (const bool sixteen : {false, true}) {
      cv::Mat base_int, templ_int, base_f, templ_f;
      // 16 bits: the full range (257 x 8-bit values reach 65535).
      p.base.convertTo(base_int, sixteen ? CV_16U : CV_8U, sixteen ? 257.0 : 1.0);
      p.templ.convertTo(templ_int, sixteen ? CV_16U : CV_8U, sixteen ? 257.0 : 1.0);
      base_int.convertTo(base_f, CV_32F);
      templ_int.convertTo(templ_f, CV_32F);
      const Eigen::Vector2d prior = p.truth + Eigen::Vector2d(7, -5);
      const ScdResult ri = matcher.Match(base_int, base_mask, templ_int, templ_mask, prior, 24);
      const ScdResult rf = matcher.Match(base_f, base_mask, templ_f, templ_mask, prior, 24);
      SCOPED_TRACE(::testing::Message()
                   << "factor " << factor << (sixteen ? " 16" : " 8") << "-bit");
      ASSERT_TRUE(ri.ok() && rf.ok()) << ri.reason << " / " << rf.reason;
      EXPECT_EQ(ri.offset.x(), rf.offset.x());
      EXPECT_EQ(ri.offset.y(), rf.offset.y());
      EXPECT_EQ(ri.peak_ratio, rf.peak_ratio);
      EXPECT_EQ(ri.overlap_px, rf.overlap_px);
      EXPECT_LT(Error(rf, p.truth), factor);  // Within one reduced pixel.
    }
  }
}

TEST(ScdTest, GainAndOffsetChangeTheResultByLessThanATenthOfAPixel) {
  const cv::Mat image = LoadFloat("thermal/seq_1_60_30/1_60_30_0_00030.jpg");
  const cv::Rect a(0, 0, 380, 300), b(230, 170, 380, 300);
  Pair p = CropPair(image, a, b, {0.3, -0.2}, {-0.1, 0.4});
  // Real noise level of a thermal frame so the noise floor matters.
  std::mt19937 rng(3);
  cv::Mat noise(p.templ.size(), CV_32F);
  cv::randn(noise, 0.0, 4.0);
  p.templ += noise;
  cv::randn(noise, 0.0, 4.0);
  p.base += noise;
  ScdMatcher matcher;
  const Eigen::Vector2d predicted = p.truth + Eigen::Vector2d(-20, 17);
  const ScdResult ref = matcher.Match(p.base, cv::Mat(), p.templ, cv::Mat(), predicted, 64);
  ASSERT_TRUE(ref.ok()) << ref.reason;
  EXPECT_LT(Error(ref, p.truth), 0.25);
  const double range = 255.0;  // Applied in float: no clipping, a pure gain/offset change.
  double worst_change = 0.0;
  for (double gain : {0.5, 0.8, 1.3, 2.0}) {
    for (double offset : {-0.3, 0.0, 0.3}) {
      const cv::Mat changed = p.templ * gain + offset * range;
      const ScdResult r = matcher.Match(p.base, cv::Mat(), changed, cv::Mat(), predicted, 64);
      ASSERT_TRUE(r.ok()) << r.reason;
      EXPECT_LT((r.offset - ref.offset).norm(), 0.1) << "gain " << gain << " offset " << offset;
      worst_change = std::max(worst_change, (r.offset - ref.offset).norm());
    }
  }
  std::printf("SCD gain/offset: error %.3f px, largest change %.3f px of 12\n", Error(ref, p.truth),
              worst_change);
}

// Footprint of a warped frame: a convex quadrilateral filling most of `size`.
cv::Mat RandomFootprint(cv::Size size, std::mt19937* rng) {
  std::uniform_real_distribution<double> inset(0.0, 0.18);
  const double w = size.width, h = size.height;
  std::vector<cv::Point> quad = {{int(inset(*rng) * w), int(inset(*rng) * h)},
                                 {int((1 - inset(*rng)) * w), int(inset(*rng) * h)},
                                 {int((1 - inset(*rng)) * w), int((1 - inset(*rng)) * h)},
                                 {int(inset(*rng) * w), int((1 - inset(*rng)) * h)}};
  cv::Mat mask = cv::Mat::zeros(size, CV_8U);
  cv::fillConvexPoly(mask, quad, cv::Scalar(255));
  return mask;
}

// Fraction of the template's valid pixels over valid base pixels at integer `offset`.
double ValidOverlap(const Pair& p, const cv::Point& offset) {
  const cv::Rect in_t = cv::Rect(0, 0, p.templ_mask.cols, p.templ_mask.rows) &
                        cv::Rect(-offset.x, -offset.y, p.base_mask.cols, p.base_mask.rows);
  if (in_t.empty()) return 0.0;
  cv::Mat both;
  cv::bitwise_and(p.templ_mask(in_t), p.base_mask(in_t + offset), both);
  return cv::countNonZero(both) / double(std::max(1, cv::countNonZero(p.templ_mask)));
}

// Frame `image` warped onto an oblique "ortho" canvas (1.8x, far edge stretched), moved by
// `sub`, with its validity.
void WarpToCanvas(const cv::Mat& image, const Eigen::Vector2d& sub, cv::Mat* ortho, cv::Mat* mask) {
  const std::vector<cv::Point2f> src = {{0, 0}, {640, 0}, {640, 512}, {0, 512}};
  const std::vector<cv::Point2f> dst = {{0, 0}, {1150, 0}, {950, 760}, {200, 760}};
  const cv::Mat shift = (cv::Mat_<double>(3, 3) << 1, 0, sub.x(), 0, 1, sub.y(), 0, 0, 1);
  const cv::Mat h = shift * cv::getPerspectiveTransform(src, dst);
  cv::warpPerspective(image, *ortho, h, cv::Size(1150, 760), cv::INTER_LINEAR);
  cv::warpPerspective(cv::Mat(image.size(), CV_8U, cv::Scalar(255)), *mask, h, cv::Size(1150, 760),
                      cv::INTER_NEAREST);
}

// Real thermal frames made orthoimage-like: PSNR 20 dB white noise added to each frame (as the
// sensor does, before the warp), template gain 0.6-1.4 and offset +-30 % of range, each frame
// warped onto an oblique canvas (the template's moved by a sub-pixel shift), two 640x512 crops
// with 15-25 % valid overlap and random warped-frame footprints as masks, pose error uniform in
// +-60 px per axis, search radius 64 px.
TEST(ScdTest, FifteenToTwentyFivePercentOverlapAtPsnr20) {
  const std::vector<std::string> frames = {
      "thermal/seq_1_60_30/1_60_30_0_00000.jpg",   "thermal/seq_1_60_30/1_60_30_0_00012.jpg",
      "thermal/seq_1_60_30/1_60_30_0_00025.jpg",   "thermal/seq_1_60_30/1_60_30_0_00037.jpg",
      "thermal/seq_1_60_30/1_60_30_0_00049.jpg",   "thermal/seq_0_100_90/0_100_90_0_08267.jpg",
      "thermal/seq_0_100_90/0_100_90_0_08282.jpg", "thermal/seq_0_100_90/0_100_90_0_08307.jpg"};
  const double noise_std = 255.0 / std::pow(10.0, 20.0 / 20.0);  // PSNR 20 dB on 8-bit range.
  const cv::Size canvas(1150, 760), size(640, 512);
  std::mt19937 rng(20);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  cv::RNG noise_rng(20);
  ScdMatcher matcher;
  // The coarse peak alone (no full-resolution refinement), as the Mosaicker's pipeline uses
  // it: fine registration (LSM) takes the translation from there.
  ScdOptions coarse_only;
  coarse_only.refine_at_full_resolution = false;
  ScdMatcher coarse_matcher(coarse_only);
  int cases = 0, good = 0, coarse_good = 0, coarse_same_status = 0;
  double coarse_worst = 0.0;
  for (const std::string& file : frames) {
    const cv::Mat frame = LoadFloat(file);
    for (int k = 0; k < 6; ++k) {
      // One draw a statement, y first (a call's argument order is unspecified; every
      // compiler draws the same scenes).
      const double sub_y = uni(rng) - 0.5;
      const Eigen::Vector2d sub(uni(rng) - 0.5, sub_y);
      const double gain = 0.6 + 0.8 * uni(rng), offset = (uni(rng) - 0.5) * 0.6 * 255.0;
      cv::Mat noise(frame.size(), CV_32F), ortho_b, ortho_t, mask_b, mask_t;
      noise_rng.fill(noise, cv::RNG::NORMAL, 0.0, noise_std);
      WarpToCanvas(frame + noise, Eigen::Vector2d::Zero(), &ortho_b, &mask_b);
      noise_rng.fill(noise, cv::RNG::NORMAL, 0.0, noise_std);
      WarpToCanvas((frame + noise) * gain + offset, sub, &ortho_t, &mask_t);
      // Crop positions with 15-25 % valid overlap (rejection sampling).
      Pair p;
      cv::Rect a, b;
      double overlap = 0.0;
      for (int attempt = 0; attempt < 5000; ++attempt) {
        const int ay = int(uni(rng) * (canvas.height - size.height));
        a = cv::Rect(cv::Point(int(uni(rng) * (canvas.width - size.width)), ay), size);
        const int by = int(uni(rng) * (canvas.height - size.height));
        b = cv::Rect(cv::Point(int(uni(rng) * (canvas.width - size.width)), by), size);
        p.base_mask = mask_b(a) & RandomFootprint(size, &rng);
        p.templ_mask = mask_t(b) & RandomFootprint(size, &rng);
        overlap = ValidOverlap(p, b.tl() - a.tl());
        if (overlap >= 0.15 && overlap <= 0.25) break;
      }
      ASSERT_GE(overlap, 0.15);
      ASSERT_LE(overlap, 0.25);
      p.base = ortho_b(a).clone();
      p.templ = ortho_t(b).clone();
      p.base.setTo(0.0f, ~p.base_mask);
      p.templ.setTo(0.0f, ~p.templ_mask);
      p.truth = Eigen::Vector2d(b.x - a.x, b.y - a.y) - sub;
      const double pose_error_y = 120.0 * (uni(rng) - 0.5);
      const Eigen::Vector2d pose_error(120.0 * (uni(rng) - 0.5), pose_error_y);
      const ScdResult r =
          matcher.Match(p.base, p.base_mask, p.templ, p.templ_mask, p.truth + pose_error, 64.0);
      ++cases;
      const double e = r.ok() ? Error(r, p.truth) : std::numeric_limits<double>::infinity();
      const ScdResult c = coarse_matcher.Match(p.base, p.base_mask, p.templ, p.templ_mask,
                                               p.truth + pose_error, 64.0);
      coarse_same_status += c.status == r.status && c.peak_ratio == r.peak_ratio;
      if (c.ok()) {
        EXPECT_EQ(c.score, 0.0);
        const double ec = Error(c, p.truth);
        coarse_good += ec < 2.0;
        if (e < 1.0) coarse_worst = std::max(coarse_worst, ec);
      }
      if (e < 1.0) {
        ++good;
      } else {
        std::printf("miss: %s case %d: %s (%s) error %.2f score %.3f ratio %.2f\n", file.c_str(), k,
                    ToString(r.status), r.reason.c_str(), e, r.score, r.peak_ratio);
      }
    }
  }
  std::printf("SCD 15-25%% overlap, PSNR 20 dB: %d of %d within 1 px\n", good, cases);
  EXPECT_GE(good, std::ceil(0.95 * cases)) << good << " of " << cases << " within 1 px";
  // Without the refinement: the same status and peak ratio (both come from the coarse
  // search); where the refined peak is within 1 px, the coarse one is within the pull-in of
  // the fine registration that follows it in the pipeline (LsmOptions::max_shift_px, 6 px;
  // measured: worst 3.2 px, 44 of 48 within 2 px against 46 of 48 within 1 px refined).
  std::printf("coarse peak only: %d of %d within 2 px, worst %.2f px where refined < 1 px\n",
              coarse_good, cases, coarse_worst);
  EXPECT_EQ(coarse_same_status, cases);
  EXPECT_GE(coarse_good, std::ceil(0.9 * cases));
  EXPECT_LT(coarse_worst, LsmOptions().max_shift_px);
}

// A simulated frame warped onto the mosaic grid by its true homography: the orthoimage, its
// validity and the mosaic pixel of its top-left pixel.
struct SimOrtho {
  cv::Mat image, mask;
  cv::Point origin;
  Eigen::Vector2d pos_error = Eigen::Vector2d::Zero();  // measured minus true centre, mosaic px
};

SimOrtho OrthoOfSimFrame(const FlightSimulator& sim, const SimFrame& frame, double psnr_db,
                         cv::RNG* noise_rng) {
  const CameraModel& cam = sim.camera();
  // Noise at psnr_db against the frame's own range (as the 8-bit range of the real frames).
  cv::Mat f32;
  frame.image.convertTo(f32, CV_32F);
  double lo = 0.0, hi = 0.0;
  cv::minMaxLoc(f32, &lo, &hi);
  cv::Mat noise(f32.size(), CV_32F);
  noise_rng->fill(noise, cv::RNG::NORMAL, 0.0, (hi - lo) / std::pow(10.0, psnr_db / 20.0));
  f32 += noise;
  const Eigen::Matrix3d& h = frame.true_mosaic_from_image;
  std::vector<cv::Point2f> corners;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(0, 0), Eigen::Vector2d(cam.width, 0),
        Eigen::Vector2d(cam.width, cam.height), Eigen::Vector2d(0, cam.height)}) {
    const Eigen::Vector3d m = h * c.homogeneous();
    corners.emplace_back(float(m.x() / m.z()), float(m.y() / m.z()));
  }
  const cv::Rect box = cv::boundingRect(corners);
  SimOrtho o;
  o.origin = box.tl();
  cv::Mat mosaic_from_image;
  const Eigen::Matrix3d canvas_from_image =
      (Eigen::Matrix3d() << 1, 0, -box.x, 0, 1, -box.y, 0, 0, 1).finished() * h;
  cv::eigen2cv(canvas_from_image, mosaic_from_image);
  cv::warpPerspective(f32, o.image, mosaic_from_image, box.size(), cv::INTER_LINEAR);
  cv::warpPerspective(cv::Mat(f32.size(), CV_8U, cv::Scalar(255)), o.mask, mosaic_from_image,
                      box.size(), cv::INTER_NEAREST);
  o.image.setTo(0.0f, ~o.mask);
  // Where the logged (erroneous) POS puts the frame centre instead.
  const FrameGeometry measured = ComputeFrameGeometry(cam, PoseFromRecord(frame.measured_pos),
                                                      sim.frame(), sim.grid(), FlatGround(0.0));
  EXPECT_TRUE(measured.ok) << measured.problem;
  const Eigen::Vector3d centre(cam.width / 2.0, cam.height / 2.0, 1.0);
  const Eigen::Vector3d m = measured.mosaic_from_image * centre, t = h * centre;
  o.pos_error = m.hnormalized() - t.hnormalized();
  return o;
}

// Simulator frames (oblique sweep, default POS errors: 2 m position, 0.3 deg attitude per
// frame), PSNR 20 dB, each orthorectified by its true pose; consecutive frames of a sweep
// (about 25 % overlap) and frames of consecutive sweeps (about 15 %). The predicted offset
// carries the pair's pose error as the logged POS gives it, search radius 64 px.
TEST(ScdTest, SimulatorFramesAtLowOverlapAndPsnr20) {
  SynthOptions options;
  options.origin_lat_deg = 47.2;
  options.origin_lon_deg = 8.5;
  options.frame_count = 32;
  options.sensor.noise = false;  // Added below at a PSNR on the frame's own range.
  FlightSimulator sim(options);
  cv::RNG noise_rng(21);
  std::vector<SimOrtho> orthos;
  for (int i = 0; i < sim.frame_count(); ++i) {
    orthos.push_back(OrthoOfSimFrame(sim, sim.Render(i), 20.0, &noise_rng));
  }
  const int per_sweep = options.frames_per_sweep;
  ScdMatcher matcher;
  int cases = 0, good = 0, low_cases = 0, low_good = 0;  // low: 15-25 % overlap
  double min_overlap = 1.0, max_overlap = 0.0, max_pos_error = 0.0;
  for (int i = 0; i < sim.frame_count(); ++i) {
    for (const int j : {i + 1, i + per_sweep}) {
      if (j >= sim.frame_count() || (j == i + 1 && j % per_sweep == 0)) continue;
      const SimOrtho &b = orthos[i], &t = orthos[j];
      const cv::Point truth_px = t.origin - b.origin;
      Pair p{b.image, b.mask, t.image, t.mask, Eigen::Vector2d(truth_px.x, truth_px.y)};
      const double overlap = ValidOverlap(p, truth_px);
      const Eigen::Vector2d pose_error = t.pos_error - b.pos_error;
      min_overlap = std::min(min_overlap, overlap);
      max_overlap = std::max(max_overlap, overlap);
      max_pos_error = std::max(max_pos_error, pose_error.cwiseAbs().maxCoeff());
      const ScdResult r =
          matcher.Match(p.base, p.base_mask, p.templ, p.templ_mask, p.truth + pose_error, 64.0);
      ++cases;
      const bool low = overlap >= 0.15 && overlap <= 0.25;
      low_cases += low;
      const double e = r.ok() ? Error(r, p.truth) : std::numeric_limits<double>::infinity();
      if (e < 1.0) {
        ++good;
        low_good += low;
      } else {
        std::printf("miss: frames %d-%d overlap %.2f: %s (%s) error %.2f score %.3f ratio %.2f\n",
                    i, j, overlap, ToString(r.status), r.reason.c_str(), e, r.score, r.peak_ratio);
      }
    }
  }
  std::printf(
      "SCD simulator pairs, overlap %.2f-%.2f, pose error up to %.1f px, PSNR 20 dB: %d of %d "
      "within 1 px (15-25 %% overlap: %d of %d)\n",
      min_overlap, max_overlap, max_pos_error, good, cases, low_good, low_cases);
  EXPECT_GE(good, std::ceil(0.95 * cases)) << good << " of " << cases << " within 1 px";
  // The case proper: enough pairs at 15-25 % overlap, and >= 95 % of them within 1 px.
  EXPECT_GE(low_cases, 20);
  EXPECT_GE(low_good, std::ceil(0.95 * low_cases)) << low_good << " of " << low_cases;
}

TEST(ScdTest, BadInputGivesAStatusWithAReason) {
  const cv::Mat image = LoadFloat("thermal/seq_1_60_30/1_60_30_0_00000.jpg");
  const cv::Mat base = image(cv::Rect(0, 0, 300, 300)).clone();
  const cv::Mat templ = image(cv::Rect(200, 150, 300, 300)).clone();
  ScdMatcher matcher;
  const Eigen::Vector2d predicted(200, 150);
  auto expect = [](const ScdResult& r, ScdResult::Status status) {
    EXPECT_EQ(r.status, status) << ToString(r.status) << ": " << r.reason;
    EXPECT_FALSE(r.reason.empty());
    EXPECT_TRUE(r.offset.allFinite());
    EXPECT_TRUE(std::isfinite(r.score) && std::isfinite(r.peak_ratio));
  };
  using S = ScdResult::Status;
  expect(matcher.Match(cv::Mat(), cv::Mat(), templ, cv::Mat(), predicted, 64), S::kBadInput);
  expect(matcher.Match(base, cv::Mat(), cv::Mat(), cv::Mat(), predicted, 64), S::kBadInput);
  const cv::Mat none = cv::Mat::zeros(templ.size(), CV_8U);
  expect(matcher.Match(base, cv::Mat(), templ, none, predicted, 64), S::kBadInput);
  expect(matcher.Match(base, none, templ, cv::Mat(), predicted, 64), S::kBadInput);
  expect(matcher.Match(base, cv::Mat(), templ, cv::Mat(), {NAN, 0}, 64), S::kBadInput);
  expect(matcher.Match(base, cv::Mat(), templ, cv::Mat(), {0, INFINITY}, 64), S::kBadInput);
  expect(matcher.Match(base, cv::Mat(), templ, cv::Mat(), predicted, NAN), S::kBadInput);
  expect(matcher.Match(base, cv::Mat(), templ, cv::Mat(), predicted, -1), S::kBadInput);
  // Far from each other: no offset in the window overlaps.
  expect(matcher.Match(base, cv::Mat(), templ, cv::Mat(), {5000, 0}, 64), S::kTooLittleOverlap);
  expect(matcher.Match(base, cv::Mat(), templ, cv::Mat(), {1e300, -1e300}, 64),
         S::kTooLittleOverlap);
  // Touching by a sliver only.
  expect(matcher.Match(base, cv::Mat(), templ, cv::Mat(), {298, 0}, 0), S::kTooLittleOverlap);
  // Mask of the wrong size or type, colour image.
  expect(matcher.Match(base, cv::Mat::ones(10, 10, CV_8U), templ, cv::Mat(), predicted, 64),
         S::kBadInput);
  cv::Mat colour;
  cv::merge(std::vector<cv::Mat>{base, base, base}, colour);
  expect(matcher.Match(colour, cv::Mat(), templ, cv::Mat(), predicted, 64), S::kBadInput);
  // Flat template (a constant plus a little noise).
  cv::Mat flat(templ.size(), CV_32F, cv::Scalar(100));
  cv::Mat noise(templ.size(), CV_32F);
  cv::randn(noise, 0.0, 2.0);
  expect(matcher.Match(base, cv::Mat(), flat + noise, cv::Mat(), predicted, 64), S::kFlat);
  // Invalid options.
  ScdOptions bad;
  bad.gradient_sigma_px = -1;
  std::string why;
  EXPECT_FALSE(bad.IsValid(&why));
  EXPECT_FALSE(why.empty());
  ScdMatcher bad_matcher(bad);
  expect(bad_matcher.Match(base, cv::Mat(), templ, cv::Mat(), predicted, 64), S::kBadInput);
  // NaN pixels in float input are treated as no data, never propagated.
  cv::Mat holed = templ.clone();
  holed(cv::Rect(20, 20, 40, 40)).setTo(NAN);
  const ScdResult r =
      matcher.Match(base, cv::Mat(), holed, cv::Mat(), predicted + Eigen::Vector2d(5, -5), 64);
  ASSERT_TRUE(r.ok()) << r.reason;
  EXPECT_LT(Error(r, {200, 150}), 0.1);
}

}  // namespace
}  // namespace irmosaic
