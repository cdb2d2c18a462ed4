// Map fusion against ground truth with an ideal-but-noisy registrar: the optimizer removes POS
// error and chaining drift; a corrupted pair is down-weighted; gains are compensated.
#include "irmosaic/map_fusion.h"

#include <ceres/autodiff_cost_function.h>
#include <ceres/loss_function.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <functional>
#include <map>
#include <mutex>
#include <opencv2/calib3d.hpp>
#include <random>
#include <thread>

#include "../src/fusion_cost.h"
#include "../src/map_fusion_testing.h"
#include "fusion_sweep.h"
#include "irmosaic/frame_geometry.h"

namespace irmosaic {
namespace {

using testing::IdealRegistrar;
using testing::MakeSweep;
using testing::PlacementRmse;
using testing::RelativeRmse;
using testing::SeamRmse;
using testing::Sweep;
using testing::SweepFrame;

struct RunResult {
  std::vector<double> rmse;      // Absolute, against the truth.
  std::vector<double> relative;  // After removing a global similarity.
  std::vector<double> seam;      // Frame j against frame j-1 (same sweep) and j-6 (previous).
  FusionStats stats;
};

// wait_for_solves: after each solve_every_frames-th frame, wait (up to a minute) until the
// optimizer has finished the solve that frame started, as on a machine fast enough for it; each
// solve then covers the same frames however fast this machine is (sanitizers, load).
RunResult RunFusion(const Sweep& s, FusionOptions options, PairRegisterFn registrar,
                    double rate_fps = 100.0, bool wait_for_solves = false) {
  options.render = false;
  MapFusion fusion(options, s.camera, std::move(registrar), nullptr);
  const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
  const auto start = std::chrono::steady_clock::now();
  for (size_t i = 0; i < s.pos.size(); ++i) {
    fusion.Push(SweepFrame(s, static_cast<int64_t>(i), image));
    const int64_t solves_due = static_cast<int64_t>(i + 1) / options.solve_every_frames;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (wait_for_solves && options.optimize && fusion.stats().solves < solves_due &&
           std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    // Frames arrive at a steady rate (100/s: 4x the sensor, the pipeline's target), not all
    // at once, so the optimizer runs behind the foreground as it would in flight.
    std::this_thread::sleep_until(
        start + std::chrono::microseconds(static_cast<int64_t>(1e6 * (i + 1) / rate_fps)));
  }
  fusion.Finish();
  RunResult result;
  for (const FramePlacement& p : fusion.Placements()) {
    result.rmse.push_back(PlacementRmse(p.mosaic_from_image, s.truth[p.index], s.camera));
  }
  result.relative = RelativeRmse(fusion.Placements(), s);
  const std::vector<FramePlacement> placements = fusion.Placements();

  for (int64_t j = 1; j < static_cast<int64_t>(placements.size()); ++j) {
    result.seam.push_back(SeamRmse(placements, s, j - 1, j));
  }
  result.stats = fusion.stats();
  return result;
}

double Mean(const std::vector<double>& v, size_t from = 0, size_t to = SIZE_MAX) {
  to = std::min(to, v.size());
  double sum = 0.0;
  for (size_t i = from; i < to; ++i) sum += v[i];
  return sum / static_cast<double>(to - from);
}

double Max(const std::vector<double>& v) { return *std::max_element(v.begin(), v.end()); }

// The run: >= 1000 frames, POS 2 m / 0.3 deg (white per frame, as the simulator draws
// it), ties with 0.15 px noise. The issue asks mean <= 0.5 px and max <= 1.5 px against the
// truth; that is below what the data allow: the Cramer-Rao bound of this network (Ceres
// covariance of a batch solve over all frames, docs/fusion.md) is 1.2 px RMS (about 1.05 px
// expected mean) at 1000 frames, and still 0.63 px RMS with perfect ties. What is asserted is
// what the fusion reaches; the figures are printed.
TEST(MapFusionTest, OptimizationRemovesPosErrorAndDrift) {
  const Sweep s = MakeSweep(1000, 6, 2.0, 0.3, 7);
  FusionOptions options;
  options.solve_every_frames = 30;
  const RunResult optimized = RunFusion(s, options, IdealRegistrar(s, 0.15, 11));
  options.optimize = false;
  const RunResult chained = RunFusion(s, options, IdealRegistrar(s, 0.15, 11), 400.0);
  std::vector<double> pos_rmse;
  for (size_t i = 0; i < s.pos.size(); ++i) {
    pos_rmse.push_back(PlacementRmse(s.pos[i], s.truth[i], s.camera));
  }
  std::printf("POS alone: mean %.3f px max %.3f px\n", Mean(pos_rmse), Max(pos_rmse));
  std::printf(
      "optimized: absolute mean %.3f max %.3f px; relative mean %.3f max %.3f px; "
      "seams mean %.3f max %.3f px; solves %lld (max %.0f ms)\n",
      Mean(optimized.rmse), Max(optimized.rmse), Mean(optimized.relative), Max(optimized.relative),
      Mean(optimized.seam), Max(optimized.seam), static_cast<long long>(optimized.stats.solves),
      optimized.stats.max_solve_ms);
  std::printf("chained: absolute first 50 %.3f px, last 50 %.3f px; seams mean %.3f max %.3f px\n",
              Mean(chained.rmse, 0, 50), Mean(chained.rmse, 950), Mean(chained.seam),
              Max(chained.seam));
  // Seams: neighbouring frames fit each other to a fraction of a pixel.
  EXPECT_LE(Mean(optimized.seam), 0.3);
  EXPECT_LE(Max(optimized.seam), 1.0);
  // Georeference: POS error (~18 px here) averaged down by an order of magnitude.
  EXPECT_LE(Mean(optimized.rmse), 0.1 * Mean(pos_rmse));
  EXPECT_LE(Max(optimized.rmse), 0.1 * Max(pos_rmse));
  // Without the optimizer, chaining drifts: the end is far worse than the start.
  EXPECT_GT(Mean(chained.rmse, 950), 2.0 * Mean(chained.rmse, 0, 50));
}

class CorruptedPairTest : public ::testing::TestWithParam<double> {};

TEST_P(CorruptedPairTest, IsDownWeighted) {
  const Sweep s = MakeSweep(240, 6, 2.0, 0.3, 3);
  FusionOptions options;
  options.solve_every_frames = 30;
  // Frame 100 registered to frame 99 with an error of GetParam() px in x on every tie point.
  const double corrupt_px = GetParam();
  const RunResult result =
      RunFusion(s, options, IdealRegistrar(s, 0.15, 5, {99, 100}, corrupt_px), 200.0);
  static const RunResult clean = RunFusion(s, options, IdealRegistrar(s, 0.15, 5), 200.0);
  std::printf(
      "corrupted pair (%.0f px): seam 99/100 %.3f px, absolute 99/100 %.3f / %.3f px "
      "(clean run: seam %.3f, absolute %.3f / %.3f)\n",
      corrupt_px, result.seam[99], result.rmse[99], result.rmse[100], clean.seam[99],
      clean.rmse[99], clean.rmse[100]);
  EXPECT_LT(result.seam[99], 1.0);  // The corruption is down-weighted below 1 px.
  EXPECT_LT(result.rmse[99], clean.rmse[99] + 1.0);
  EXPECT_LT(result.rmse[100], clean.rmse[100] + 1.0);
}

INSTANTIATE_TEST_SUITE_P(MapFusionTest, CorruptedPairTest, ::testing::Values(3.0, 6.0, 12.0));

// The lag figures say how far the disk is behind the solution: with no re-render budget every
// frame is re-rendered once it moved more than the threshold, so its seams on disk are off by
// less than the threshold at each end (RMS well below); with a budget of one frame per solve the
// disk falls behind.
// FusionOptions::short_window_frames: most background solves refine the newest frames only,
// one in full_window_every (and the final solve) the whole window; the frames further back
// have converged, so the placements come out as when every solve refines the whole window.
TEST(MapFusionTest, ShortSolvesLeaveThePlacementsAsFullOnes) {
  const Sweep s = MakeSweep(192, 6, 2.0, 0.3, 5);
  FusionOptions options;
  options.window_frames = 48;
  options.solve_every_frames = 8;
  options.short_window_frames = 0;
  // Each solve covers the same frames however fast the machine (TSan's slowness once let the
  // optimizer fall behind in one run and not the other).
  const RunResult full = RunFusion(s, options, IdealRegistrar(s, 0.15, 9), 50.0, true);
  options.short_window_frames = 12;
  options.full_window_every = 4;
  const RunResult part = RunFusion(s, options, IdealRegistrar(s, 0.15, 9), 50.0, true);
  std::printf(
      "every solve over the window: mean %.3f max %.3f px, %lld solves; short solves: mean %.3f "
      "max %.3f px, %lld solves, %lld over the whole window\n",
      Mean(full.rmse), Max(full.rmse), static_cast<long long>(full.stats.solves), Mean(part.rmse),
      Max(part.rmse), static_cast<long long>(part.stats.solves),
      static_cast<long long>(part.stats.full_solves));
  EXPECT_EQ(full.stats.full_solves, full.stats.solves);
  // The final solve and at least one background solve refined the whole window; most did not.
  EXPECT_GE(part.stats.full_solves, 2);
  EXPECT_LT(part.stats.full_solves, part.stats.solves);
  // Against the truth (POS ~18 px here; a 48-frame window leaves ~2 px): as close as the full
  // solves, the mean within 5 % and the worst frame within 15 % (which solve refined a frame
  // last differs, and so does its error, by a fraction of that error).
  EXPECT_LE(Mean(part.rmse), 1.05 * Mean(full.rmse));
  EXPECT_LE(Max(part.rmse), 1.15 * Max(full.rmse));
  EXPECT_LE(Max(part.seam), 1.0);
}

// FusionOptions::solve_iterations: each background solve starts from the placements the last
// one left and solves come every few frames, so 3 Levenberg-Marquardt iterations per stage
// reach what 6 reach (the final solve takes 20 in both).
TEST(MapFusionTest, ThreeIterationsPerSolveReachThePlacementsOfSix) {
  const Sweep s = MakeSweep(192, 6, 2.0, 0.3, 5);
  FusionOptions options;
  options.window_frames = 48;
  options.solve_every_frames = 8;
  options.solve_iterations = 6;
  const RunResult six = RunFusion(s, options, IdealRegistrar(s, 0.15, 9), 50.0, true);
  options.solve_iterations = 3;
  const RunResult three = RunFusion(s, options, IdealRegistrar(s, 0.15, 9), 50.0, true);
  std::printf(
      "6 iterations per stage: mean %.3f max %.3f px, seams max %.3f px, %lld solves, %.0f CPU "
      "ms; 3: mean %.3f max %.3f px, seams max %.3f px, %lld solves, %.0f CPU ms\n",
      Mean(six.rmse), Max(six.rmse), Max(six.seam), static_cast<long long>(six.stats.solves),
      six.stats.total_solve_cpu_ms, Mean(three.rmse), Max(three.rmse), Max(three.seam),
      static_cast<long long>(three.stats.solves), three.stats.total_solve_cpu_ms);
  EXPECT_EQ(three.stats.solves, six.stats.solves);
  // Against the truth (POS ~18 px; a 48-frame window leaves ~2 px), within the bounds of
  // ShortSolvesLeaveThePlacementsAsFullOnes.
  EXPECT_LE(Mean(three.rmse), 1.05 * Mean(six.rmse));
  EXPECT_LE(Max(three.rmse), 1.15 * Max(six.rmse));
  EXPECT_LE(Max(three.seam), 1.0);
}

// The default sparse library (Eigen's, single-threaded; docs/fusion.md, "Sparse solver") solves
// the same normal equations as SuiteSparse's CHOLMOD: the placements agree to round-off.
TEST(MapFusionTest, EigenAndSuiteSparseSolvesReachTheSamePlacements) {
  const Sweep s = MakeSweep(96, 6, 2.0, 0.3, 7);
  FusionOptions options;
  options.window_frames = 48;
  options.solve_every_frames = 8;
  ASSERT_EQ(options.sparse_library, "EIGEN_SPARSE");
  const RunResult eigen = RunFusion(s, options, IdealRegistrar(s, 0.15, 9), 50.0, true);
  options.sparse_library = "SUITE_SPARSE";
  const RunResult cholmod = RunFusion(s, options, IdealRegistrar(s, 0.15, 9), 50.0, true);
  ASSERT_EQ(eigen.rmse.size(), cholmod.rmse.size());
  double largest_difference = 0.0;
  for (size_t i = 0; i < eigen.rmse.size(); ++i) {
    largest_difference = std::max(largest_difference, std::abs(eigen.rmse[i] - cholmod.rmse[i]));
  }
  std::printf(
      "Eigen: mean %.4f px, SuiteSparse: mean %.4f px, largest per-frame difference %.2g px\n",
      Mean(eigen.rmse), Mean(cholmod.rmse), largest_difference);
  EXPECT_EQ(eigen.stats.solves, cholmod.stats.solves);
  EXPECT_LT(largest_difference, 1e-3);
  EXPECT_LT(Mean(eigen.rmse), 2.0);  // POS alone is ~18 px off (MakeSweep's 2 m, 0.3 deg).
}

TEST(MapFusionTest, SeamLagOnDiskFollowsTheRerenderBudget) {
  const Sweep s = MakeSweep(240, 6, 2.0, 0.3, 3);
  FusionOptions options;
  options.solve_every_frames = 10;
  options.max_rerenders_per_solve = 0;
  const RunResult unlimited = RunFusion(s, options, IdealRegistrar(s, 0.15, 5), 200.0);
  options.max_rerenders_per_solve = 1;
  const RunResult one = RunFusion(s, options, IdealRegistrar(s, 0.15, 5), 200.0);
  std::printf(
      "seam lag: unlimited %.3f px (frames %.3f, %lld re-renders), one per solve %.3f px (frames "
      "%.3f, %lld re-renders)\n",
      unlimited.stats.mean_seam_lag_px, unlimited.stats.mean_painted_lag_px,
      static_cast<long long>(unlimited.stats.rerendered_frames), one.stats.mean_seam_lag_px,
      one.stats.mean_painted_lag_px, static_cast<long long>(one.stats.rerendered_frames));
  ASSERT_GT(unlimited.stats.solves, 3);
  EXPECT_LE(unlimited.stats.mean_painted_lag_px, options.rerender_threshold_px);
  EXPECT_LE(unlimited.stats.mean_seam_lag_px, 2 * options.rerender_threshold_px);
  EXPECT_GT(one.stats.mean_seam_lag_px, 2.0 * unlimited.stats.mean_seam_lag_px);
  EXPECT_GT(one.stats.mean_painted_lag_px, options.rerender_threshold_px);
}

// The optimizer's costs as first written, differentiated by autodiff: the update applied in
// normalized coordinates, back to pixels, then through the reference homography (a different
// order of products from src/fusion_cost.h, so a slip in either shows).
template <typename T>
void ReferenceMapPoint(const Eigen::Matrix3d& h_ref, const fusion::Normalizer& n, const T* delta,
                       const Eigen::Vector2d& p, T* out) {
  const T nx = T((p.x() - n.cx) / n.s), ny = T((p.y() - n.cy) / n.s);
  const T mx = (T(1) + delta[0]) * nx + delta[1] * ny + delta[2];
  const T my = delta[3] * nx + (T(1) + delta[4]) * ny + delta[5];
  const T mw = delta[6] * nx + delta[7] * ny + T(1);
  const T ux = T(n.s) * mx + T(n.cx) * mw, uy = T(n.s) * my + T(n.cy) * mw, uw = mw;
  const T qx = T(h_ref(0, 0)) * ux + T(h_ref(0, 1)) * uy + T(h_ref(0, 2)) * uw;
  const T qy = T(h_ref(1, 0)) * ux + T(h_ref(1, 1)) * uy + T(h_ref(1, 2)) * uw;
  const T qw = T(h_ref(2, 0)) * ux + T(h_ref(2, 1)) * uy + T(h_ref(2, 2)) * uw;
  out[0] = qx / qw;
  out[1] = qy / qw;
}

struct ReferenceTie {
  template <typename T>
  bool operator()(const T* da, const T* db, T* residual) const {
    T qa[2], qb[2];
    ReferenceMapPoint(ha, n, da, pa, qa);
    ReferenceMapPoint(hb, n, db, pb, qb);
    residual[0] = (qa[0] - qb[0]) * T(inv_sigma);
    residual[1] = (qa[1] - qb[1]) * T(inv_sigma);
    return true;
  }
  Eigen::Matrix3d ha, hb;
  fusion::Normalizer n;
  Eigen::Vector2d pa, pb;
  double inv_sigma;
};

struct ReferencePrior {
  template <typename T>
  bool operator()(const T* d, T* residual) const {
    T e[10];
    for (int k = 0; k < 5; ++k) {
      T q[2];
      ReferenceMapPoint(h, n, d, points[k], q);
      e[2 * k] = q[0] - T(targets(2 * k));
      e[2 * k + 1] = q[1] - T(targets(2 * k + 1));
    }
    for (int r = 0; r < 10; ++r) {
      T sum = T(0);
      for (int c = 0; c <= r; ++c) sum += T(sqrt_info(r, c)) * e[c];
      residual[r] = sum;
    }
    return true;
  }
  Eigen::Matrix3d h;
  fusion::Normalizer n;
  std::array<Eigen::Vector2d, 5> points;
  Eigen::Matrix<double, 10, 1> targets;
  Eigen::Matrix<double, 10, 10> sqrt_info;
};

// Largest difference between two arrays relative to the largest magnitude in `expected`.
double RelativeDifference(const double* actual, const double* expected, int size) {
  double difference = 0.0, scale = 1e-300;
  for (int k = 0; k < size; ++k) {
    difference = std::max(difference, std::abs(actual[k] - expected[k]));
    scale = std::max(scale, std::abs(expected[k]));
  }
  return difference / scale;
}

// A placement as the fusion meets them: about 1 mosaic px per image px, rotated, far from the
// mosaic origin, a little perspective.
Eigen::Matrix3d RandomPlacement(std::mt19937& rng) {
  std::normal_distribution<double> noise(0.0, 1.0);
  const double angle = 3.0 * noise(rng), scale = 1.0 + 0.2 * noise(rng);
  Eigen::Matrix3d h;
  h << scale * std::cos(angle), -scale * std::sin(angle), 5000.0 + 2000.0 * noise(rng),
      scale * std::sin(angle), scale * std::cos(angle), 3000.0 + 2000.0 * noise(rng),
      2e-5 * noise(rng), 2e-5 * noise(rng), 1.0;
  return h;
}

TEST(MapFusionTest, AnalyticCostJacobiansMatchAutodiff) {
  const fusion::Normalizer n{319.5, 255.5, 320.0};
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> pixel_x(0.0, 639.0), pixel_y(0.0, 511.0);
  std::normal_distribution<double> noise(0.0, 1.0);
  double worst_residual = 0.0, worst_jacobian = 0.0;
  for (int trial = 0; trial < 200; ++trial) {
    // Deltas from zero (the first iteration of each solve) to well past what a solve moves.
    std::array<double, 8> da{}, db{};
    const double delta_scale = trial == 0 ? 0.0 : 0.05 * (trial % 4) / 3.0;
    for (int k = 0; k < 8; ++k) {
      da[k] = delta_scale * noise(rng) * (k >= 6 ? 0.1 : 1.0);
      db[k] = delta_scale * noise(rng) * (k >= 6 ? 0.1 : 1.0);
    }
    const double* parameters[2] = {da.data(), db.data()};

    ReferenceTie tie{RandomPlacement(rng),
                     RandomPlacement(rng),
                     n,
                     {pixel_x(rng), pixel_y(rng)},
                     {pixel_x(rng), pixel_y(rng)},
                     1.0 / (0.1 + std::abs(noise(rng)))};
    const fusion::TieCost analytic_tie(tie.ha, tie.hb, n, tie.pa, tie.pb, tie.inv_sigma);
    const ceres::AutoDiffCostFunction<ReferenceTie, 2, 8, 8> autodiff_tie(new ReferenceTie(tie));
    double r_analytic[2], r_autodiff[2], ja[16], jb[16], ja_ref[16], jb_ref[16];
    double* jacobians[2] = {ja, jb};
    double* jacobians_ref[2] = {ja_ref, jb_ref};
    ASSERT_TRUE(analytic_tie.Evaluate(parameters, r_analytic, jacobians));
    ASSERT_TRUE(autodiff_tie.Evaluate(parameters, r_autodiff, jacobians_ref));
    // Residuals are compared on the scale of the mapped points (mosaic px / sigma): a residual
    // near zero is a difference of two large numbers.
    const double point_scale = tie.inv_sigma * 1e4;
    for (int k = 0; k < 2; ++k) {
      worst_residual =
          std::max(worst_residual, std::abs(r_analytic[k] - r_autodiff[k]) / point_scale);
    }
    worst_jacobian = std::max(
        {worst_jacobian, RelativeDifference(ja, ja_ref, 16), RelativeDifference(jb, jb_ref, 16)});
    // The same residual without Jacobians, and with one block held constant (frozen frames).
    double r_plain[2];
    ASSERT_TRUE(analytic_tie.Evaluate(parameters, r_plain, nullptr));
    EXPECT_EQ(r_plain[0], r_analytic[0]);
    EXPECT_EQ(r_plain[1], r_analytic[1]);
    double jb_only[16];
    double* one_block[2] = {nullptr, jb_only};
    ASSERT_TRUE(analytic_tie.Evaluate(parameters, r_plain, one_block));
    for (int k = 0; k < 16; ++k) EXPECT_EQ(jb_only[k], jb[k]);
    // The residual is what the published placements (ApplyDelta) give.
    const Eigen::Vector2d published =
        (ApplyHomography(fusion::ApplyDelta(tie.ha, n, da.data()), tie.pa) -
         ApplyHomography(fusion::ApplyDelta(tie.hb, n, db.data()), tie.pb)) *
        tie.inv_sigma;
    worst_residual =
        std::max(worst_residual,
                 (published - Eigen::Vector2d(r_analytic[0], r_analytic[1])).norm() / point_scale);

    ReferencePrior prior;
    prior.h = tie.ha;
    prior.n = n;
    prior.points = {Eigen::Vector2d(0, 0), Eigen::Vector2d(639, 0), Eigen::Vector2d(639, 511),
                    Eigen::Vector2d(0, 511), Eigen::Vector2d(319.5, 255.5)};
    for (int k = 0; k < 10; ++k) prior.targets(k) = 4000.0 + 100.0 * noise(rng);
    // A full matrix: only its lower triangle counts, in both forms.
    for (int r = 0; r < 10; ++r) {
      for (int c = 0; c < 10; ++c) prior.sqrt_info(r, c) = (r == c ? 1.0 : 0.3) * noise(rng);
    }
    const fusion::PriorCost analytic_prior(prior.h, n, prior.points, prior.targets,
                                           prior.sqrt_info);
    const ceres::AutoDiffCostFunction<ReferencePrior, 10, 8> autodiff_prior(
        new ReferencePrior(prior));
    double p_analytic[10], p_autodiff[10], jp[80], jp_ref[80];
    double* prior_jacobians[1] = {jp};
    double* prior_jacobians_ref[1] = {jp_ref};
    ASSERT_TRUE(analytic_prior.Evaluate(parameters, p_analytic, prior_jacobians));
    ASSERT_TRUE(autodiff_prior.Evaluate(parameters, p_autodiff, prior_jacobians_ref));
    const double prior_scale = 1e4 * prior.sqrt_info.lpNorm<Eigen::Infinity>();
    for (int k = 0; k < 10; ++k) {
      worst_residual =
          std::max(worst_residual, std::abs(p_analytic[k] - p_autodiff[k]) / prior_scale);
    }
    worst_jacobian = std::max(worst_jacobian, RelativeDifference(jp, jp_ref, 80));
    double p_plain[10];
    ASSERT_TRUE(analytic_prior.Evaluate(parameters, p_plain, nullptr));
    for (int k = 0; k < 10; ++k) EXPECT_EQ(p_plain[k], p_analytic[k]);
  }
  std::printf("analytic vs autodiff: residuals %.2e, Jacobians %.2e (relative)\n", worst_residual,
              worst_jacobian);
  EXPECT_LE(worst_residual, 1e-12);
  EXPECT_LE(worst_jacobian, 1e-9);
}

// One tie under a pair's robust loss, as PairTieCost scales it (for autodiff): the tie's
// residual r times sqrt(rho(s) / s), s = |r|^2, rho = w s or w b^2 log(1 + s / b^2).
struct ReferenceScaledTie {
  template <typename T>
  bool operator()(const T* da, const T* db, T* residual) const {
    T r[2];
    tie(da, db, r);
    const T s = r[0] * r[0] + r[1] * r[1];
    T g = T(loss.weight);
    if (loss.cauchy_scale > 0.0) {
      const double b2 = loss.cauchy_scale * loss.cauchy_scale;
      g = T(loss.weight * b2) * log1p(s / T(b2)) / s;
    }
    residual[0] = sqrt(g) * r[0];
    residual[1] = sqrt(g) * r[1];
    return true;
  }
  ReferenceTie tie;
  fusion::TieLoss loss;
};

// rho(s) / s and its derivative near s = 0 against their series, and across the switch from
// the series to the closed form.
TEST(MapFusionTest, RobustRatioFollowsTheCauchyLossAtAnyResidual) {
  const fusion::TieLoss loss{0.7, 3.0};
  const double b2 = 9.0;
  double worst_g = 0.0, worst_dg = 0.0;
  for (double x = 1e-12; x <= 1e-2; x *= 1.7) {
    double g_series = 0.0, dg_series = 0.0, power = 1.0;
    for (int k = 0; k < 12; ++k) {  // log1p(x) / x = sum (-x)^k / (k + 1).
      g_series += power / (k + 1);
      if (k + 1 < 12) dg_series += (k % 2 == 0 ? -1.0 : 1.0) * (k + 1) * std::pow(x, k) / (k + 2);
      power *= -x;
    }
    double g, dg;
    fusion::RobustRatio(loss, x * b2, &g, &dg);
    worst_g = std::max(worst_g, std::abs(g / (loss.weight * g_series) - 1.0));
    worst_dg = std::max(worst_dg, std::abs(dg / (loss.weight * dg_series / b2) - 1.0));
  }
  std::printf("rho(s)/s against its series: %.1e, its derivative %.1e (relative)\n", worst_g,
              worst_dg);
  EXPECT_LE(worst_g, 1e-12);
  EXPECT_LE(worst_dg, 1e-6);
  // Least squares: the weight, flat.
  double g, dg;
  fusion::RobustRatio({0.4, 0.0}, 123.0, &g, &dg);
  EXPECT_EQ(g, 0.4);
  EXPECT_EQ(dg, 0.0);
}

// A pair's ties in one residual block: its squared norm is the sum of the ties' robust costs
// (as ceres::ScaledLoss over ceres::CauchyLoss gives them), its gradient Ceres' for one block
// per tie, its Jacobian autodiff's of the scaled residual.
TEST(MapFusionTest, OneBlockPerPairGivesEachTiesRobustCostGradientAndJacobian) {
  const fusion::Normalizer n{319.5, 255.5, 320.0};
  std::mt19937 rng(29);
  std::uniform_real_distribution<double> pixel_x(0.0, 639.0), pixel_y(0.0, 511.0), unit(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, 1.0);
  double worst_cost = 0.0, worst_gradient = 0.0, worst_jacobian = 0.0;
  int ties_seen = 0;
  for (int trial = 0; trial < 120; ++trial) {
    const Eigen::Matrix3d ha = RandomPlacement(rng);
    Eigen::Matrix3d hb = ha;  // Overlapping frames: b shifted and turned a little against a.
    const double shift_y =
        200.0 * noise(rng);  // One draw a statement: the same for every compiler.
    hb.col(2) += Eigen::Vector3d(300.0 * noise(rng), shift_y, 0.0);
    const double inv_sigma = 1.0 / (0.1 + std::abs(noise(rng)));
    const fusion::TieLoss loss{0.05 + 0.95 * unit(rng), trial % 3 == 0 ? 0.0 : 3.0};
    const int count = 1 + trial % 24;
    std::vector<Eigen::Vector2d> pa, pb;
    for (int t = 0; t < count; ++t) {
      const double y = pixel_y(rng);
      pa.emplace_back(pixel_x(rng), y);
      // The tie's partner where b's placement puts a's point, off by 0.02 to 50 sigma.
      const Eigen::Vector2d on_mosaic = ApplyHomography(ha, pa.back());
      const double off = 0.02 * std::pow(2500.0, unit(rng)) / inv_sigma;
      const double angle = 6.283 * unit(rng);
      pb.push_back(ApplyHomography(hb.inverse(), on_mosaic) +
                   off * Eigen::Vector2d(std::cos(angle), std::sin(angle)));
    }
    std::array<double, 8> da{}, db{};
    for (int k = 0; k < 8; ++k) {
      da[k] = 1e-4 * noise(rng) * (k >= 6 ? 0.1 : 1.0);
      db[k] = 1e-4 * noise(rng) * (k >= 6 ? 0.1 : 1.0);
    }
    const double* parameters[2] = {da.data(), db.data()};
    const fusion::PairTieCost pair(ha, hb, n, pa, pb, inv_sigma, &loss);
    ASSERT_EQ(pair.num_residuals(), 2 * count);
    std::vector<double> r(2 * count), ja(16 * count), jb(16 * count);
    double* jacobians[2] = {ja.data(), jb.data()};
    ASSERT_TRUE(pair.Evaluate(parameters, r.data(), jacobians));

    ceres::ScaledLoss rho(
        loss.cauchy_scale > 0.0 ? new ceres::CauchyLoss(loss.cauchy_scale) : nullptr, loss.weight,
        ceres::TAKE_OWNERSHIP);
    double cost = 0.0;
    Eigen::Matrix<double, 16, 1> gradient = Eigen::Matrix<double, 16, 1>::Zero();
    for (int t = 0; t < count; ++t) {
      ReferenceTie tie{ha, hb, n, pa[t], pb[t], inv_sigma};
      const fusion::TieCost one(ha, hb, n, pa[t], pb[t], inv_sigma);
      double r_tie[2], ja_tie[16], jb_tie[16];
      double* tie_jacobians[2] = {ja_tie, jb_tie};
      ASSERT_TRUE(one.Evaluate(parameters, r_tie, tie_jacobians));
      double rho_tie[3];
      rho.Evaluate(r_tie[0] * r_tie[0] + r_tie[1] * r_tie[1], rho_tie);
      cost += rho_tie[0];
      for (int c = 0; c < 8; ++c) {
        gradient(c) += rho_tie[1] * (ja_tie[c] * r_tie[0] + ja_tie[8 + c] * r_tie[1]);
        gradient(8 + c) += rho_tie[1] * (jb_tie[c] * r_tie[0] + jb_tie[8 + c] * r_tie[1]);
      }
      const ceres::AutoDiffCostFunction<ReferenceScaledTie, 2, 8, 8> reference(
          new ReferenceScaledTie{tie, loss});
      double r_ref[2], ja_ref[16], jb_ref[16];
      double* ref_jacobians[2] = {ja_ref, jb_ref};
      ASSERT_TRUE(reference.Evaluate(parameters, r_ref, ref_jacobians));
      worst_jacobian = std::max({worst_jacobian, RelativeDifference(&ja[16 * t], ja_ref, 16),
                                 RelativeDifference(&jb[16 * t], jb_ref, 16)});
      ++ties_seen;
    }
    double norm = 0.0;
    for (double v : r) norm += v * v;
    worst_cost = std::max(worst_cost, std::abs(norm - cost) / cost);
    Eigen::Matrix<double, 16, 1> block_gradient = Eigen::Matrix<double, 16, 1>::Zero();
    for (int row = 0; row < 2 * count; ++row) {
      for (int c = 0; c < 8; ++c) {
        block_gradient(c) += ja[8 * row + c] * r[row];
        block_gradient(8 + c) += jb[8 * row + c] * r[row];
      }
    }
    worst_gradient = std::max(worst_gradient, (block_gradient - gradient).norm() / gradient.norm());

    // Residuals alone are the same; a frozen frame's block (null) leaves the other's as it was.
    std::vector<double> r_plain(2 * count), jb_only(16 * count);
    ASSERT_TRUE(pair.Evaluate(parameters, r_plain.data(), nullptr));
    EXPECT_EQ(r_plain, r);
    double* one_block[2] = {nullptr, jb_only.data()};
    ASSERT_TRUE(pair.Evaluate(parameters, r_plain.data(), one_block));
    EXPECT_EQ(jb_only, jb);
  }
  std::printf("one block per pair (%d ties): cost %.1e, gradient %.1e, Jacobian %.1e (relative)\n",
              ties_seen, worst_cost, worst_gradient, worst_jacobian);
  EXPECT_LE(worst_cost, 1e-12);
  EXPECT_LE(worst_gradient, 1e-9);
  EXPECT_LE(worst_jacobian, 1e-9);
}

// Frames older than the newest candidate_frames (and the window) keep no image: they are no
// registration candidates (a revisit of their ground registers to newer frames only) but stay
// held as frozen ends of pairs, and the images held stay bounded however long the flight.
TEST(MapFusionTest, HeldImagesAreBoundedByTheCandidates) {
  const Sweep s = MakeSweep(30, 6, 0.0, 0.0, 11);
  FusionOptions options;
  options.window_frames = 8;
  options.optimize = false;  // No solve: which frames are refined cannot depend on timing.
  options.render = false;
  std::vector<std::pair<int64_t, int64_t>> calls;  // (base, template)
  const PairRegisterFn record = [&calls](const FusionFrame& base, const FusionFrame& templ) {
    calls.emplace_back(base.index, templ.index);
    PairMatch m;
    m.reason = "not registered in this test";
    return m;
  };
  MapFusion fusion(options, s.camera, record, nullptr);
  auto push = [&](int64_t index, size_t pose) {
    FusionFrame f;
    f.index = index;
    f.time_s = static_cast<double>(index) * 0.04;
    f.image = cv::Mat(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000 + index));
    f.pos_mosaic_from_image = s.pos[pose];
    fusion.Push(std::move(f));
  };
  const int64_t image_bytes = int64_t{2} * s.camera.width * s.camera.height;
  for (int64_t i = 0; i < 30; ++i) {
    push(i, static_cast<size_t>(i));
    const FusionStats stats = fusion.stats();
    ASSERT_EQ(stats.held_images, std::min<int64_t>(i + 1, 8)) << "after frame " << i;
    ASSERT_EQ(stats.held_image_bytes, stats.held_images * image_bytes);
    ASSERT_EQ(stats.held_frames, std::min<int64_t>(i + 1, 16)) << "after frame " << i;
  }
  // Frame 30 flies over frame 18's ground again: 18 is held (frozen) but 12 frames back, past
  // the 8 candidates, so only the newer frames that overlap it are tried.
  calls.clear();
  push(30, 18);
  ASSERT_FALSE(calls.empty());
  for (const auto& [base, templ] : calls) EXPECT_GE(base, 30 - 8) << "registered to " << base;
  // Frame 31 over frame 27's ground, 4 frames back: a candidate, the best overlap.
  calls.clear();
  push(31, 27);
  EXPECT_NE(std::find(calls.begin(), calls.end(), std::pair<int64_t, int64_t>{27, 31}),
            calls.end());
  EXPECT_EQ(fusion.stats().held_images, 8);
  EXPECT_EQ(fusion.stats().held_frames, 16);
}

// Pairs of a new frame registered at once: the same placements, in the same order, as one
// at a time; the registrar really runs concurrently; a failure of any pair reaches the caller.
TEST(MapFusionTest, PairsRegisteredAtOnceGiveTheSamePlacements) {
  const Sweep s = MakeSweep(24, 6, 2.0, 0.3, 5);
  std::atomic<int> in_flight{0}, most_in_flight{0};
  std::atomic<int64_t> throw_for_template{-1};
  std::atomic<bool> await_overlap{false};
  std::atomic<int> waited_ms{0};  // Of all calls together.
  // Ties from the truth with noise seeded by the pair alone, so the order of the calls cannot
  // change them. With await_overlap, a call waits (up to 50 ms, 2 s for all calls) until two
  // have been in flight at once: a helper thread slow to start on a loaded machine cannot hide
  // the overlap, and with one registration at a time the waits time out and the count stays 1.
  const PairRegisterFn registrar = [&](const FusionFrame& base, const FusionFrame& templ) {
    const int now = ++in_flight;
    for (int seen = most_in_flight.load(); now > seen;) {
      if (most_in_flight.compare_exchange_weak(seen, now)) break;
    }
    for (int ms = 0; await_overlap && most_in_flight < 2 && ms < 50 && ++waited_ms <= 2000; ++ms) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    if (most_in_flight >= 2) await_overlap = false;
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
    --in_flight;
    if (templ.index == throw_for_template && base.index != templ.index - 1) {
      throw std::runtime_error("registrar failure for frame " + std::to_string(templ.index));
    }
    return PairSeededTies(s, base, templ);
  };
  auto run = [&](int threads) {
    FusionOptions options;
    options.optimize = false;  // The chained placements alone: no timing dependence.
    options.render = false;
    options.registration_threads = threads;
    MapFusion fusion(options, s.camera, registrar, nullptr);
    std::vector<FramePlacement> placements;
    for (int64_t i = 0; i < 24; ++i) {
      FusionFrame f;
      f.index = i;
      f.time_s = static_cast<double>(i) * 0.04;
      f.image = cv::Mat(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
      f.pos_mosaic_from_image = s.pos[static_cast<size_t>(i)];
      placements.push_back(fusion.Push(std::move(f)));
    }
    return placements;
  };
  const std::vector<FramePlacement> one = run(1);
  EXPECT_EQ(most_in_flight, 1);
  most_in_flight = 0;
  await_overlap = true;
  const std::vector<FramePlacement> two = run(2);
  await_overlap = false;
  EXPECT_EQ(most_in_flight, 2);
  ASSERT_EQ(one.size(), two.size());
  int registered_to_two = 0;
  for (size_t k = 0; k < one.size(); ++k) {
    EXPECT_EQ(one[k].neighbours, two[k].neighbours) << "frame " << k;
    EXPECT_EQ(one[k].mosaic_from_image, two[k].mosaic_from_image) << "frame " << k;
    EXPECT_EQ(one[k].inliers, two[k].inliers) << "frame " << k;
    registered_to_two += two[k].neighbours.size() == 2 ? 1 : 0;
  }
  EXPECT_GE(registered_to_two, 12);  // Most frames have two neighbours to register at once.
  // A registrar that throws for the second pair of frame 10 (run on a helper thread, or on
  // the caller's): Push reports it, after both pairs finished.
  throw_for_template = 10;
  FusionOptions options;
  options.optimize = false;
  options.render = false;
  options.registration_threads = 2;
  MapFusion fusion(options, s.camera, registrar, nullptr);
  for (int64_t i = 0; i <= 10; ++i) {
    FusionFrame f;
    f.index = i;
    f.time_s = static_cast<double>(i) * 0.04;
    f.image = cv::Mat(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
    f.pos_mosaic_from_image = s.pos[static_cast<size_t>(i)];
    if (i < 10) {
      fusion.Push(std::move(f));
    } else {
      EXPECT_THROW(fusion.Push(std::move(f)), std::runtime_error);
    }
  }
  EXPECT_EQ(in_flight, 0);
}

// Held images on disk (images_in_memory): each frame a registration or a re-render reads back
// is that frame's own image, the radiometric ties and placements are those of a run with every
// image in memory, and the file is never linked into its folder.
TEST(MapFusionTest, HeldImagesOnDiskComeBackForPairsAndRerenders) {
  const Sweep s = MakeSweep(48, 6, 2.0, 0.3, 17);
  const std::filesystem::path dir = std::filesystem::temp_directory_path() /
                                    ("irmosaic_fusion_spill_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  auto value_of = [](int64_t index) { return 1000.0 + 7.0 * static_cast<double>(index); };
  auto image_of = [&](int64_t index) {
    return cv::Mat(s.camera.height, s.camera.width, CV_16U, cv::Scalar(value_of(index)));
  };
  // Checks every base image the registrar gets against the frame's own.
  // A fresh registrar per run: its tie noise comes from one generator in call order.
  std::atomic<int> wrong_bases{0}, calls{0};
  auto checking = [&]() -> PairRegisterFn {
    PairRegisterFn ideal = IdealRegistrar(s, 0.2, 3);
    return [&, ideal](const FusionFrame& base, const FusionFrame& templ) {
      ++calls;
      double low = 0, high = 0;
      cv::minMaxLoc(base.image, &low, &high);
      if (base.image.empty() || low != value_of(base.index) || high != low) ++wrong_bases;
      return ideal(base, templ);
    };
  };
  // Checks every painted pixel against the value of the frame placed next (Paint precedes
  // FramePlaced for the same frame, on the same thread).
  struct CheckingSink : MosaicSink {
    std::function<double(int64_t)> value_of;
    std::mutex mu;
    std::map<std::thread::id, std::pair<double, double>> painted;  // min, max painted value
    int wrong = 0, checked = 0;
    int first_paints = 0, repaints = 0;  // Paint (a frame's first) and Repaint (re-renders).
    void Record(const cv::Mat& image, const cv::Mat& weight, int* count) {
      double low = 0, high = 0;
      cv::minMaxLoc(image, &low, &high, nullptr, nullptr, weight > 0);
      std::lock_guard<std::mutex> lock(mu);
      painted[std::this_thread::get_id()] = {low, high};
      ++*count;
    }
    void Paint(const cv::Mat& image, const cv::Mat& weight, cv::Point) override {
      Record(image, weight, &first_paints);
    }
    void Repaint(const cv::Mat& image, const cv::Mat& weight, cv::Point) override {
      Record(image, weight, &repaints);
    }
    void FramePlaced(const FramePlacement& p) override {
      std::lock_guard<std::mutex> lock(mu);
      auto it = painted.find(std::this_thread::get_id());
      if (it == painted.end()) return;
      const double expected = value_of(p.index);
      if (std::abs(it->second.first - expected) > 1 || std::abs(it->second.second - expected) > 1) {
        ++wrong;
      }
      ++checked;
      painted.erase(it);
    }
  };
  auto run = [&](int in_memory, bool optimize, CheckingSink* sink, FusionStats* stats) {
    FusionOptions options;
    options.window_frames = 12;
    options.solve_every_frames = 3;
    options.rerender_threshold_px = 0.0;  // Every frame a solve moves is painted again.
    options.compensate_gain = false;      // Painted values are the frame's own.
    options.optimize = optimize;
    options.images_in_memory = in_memory;
    options.spill_directory = dir.string();
    std::vector<FramePlacement> placements;
    {
      MapFusion fusion(options, s.camera, checking(), sink);
      for (int64_t i = 0; i < 48; ++i) {
        FusionFrame f;
        f.index = i;
        f.time_s = static_cast<double>(i) * 0.04;
        f.image = image_of(i);
        f.pos_mosaic_from_image = s.pos[static_cast<size_t>(i)];
        fusion.Push(std::move(f));
        if (in_memory > 0 && i >= in_memory) {
          const FusionStats now = fusion.stats();
          EXPECT_LE(now.held_images, in_memory) << "after frame " << i;
          EXPECT_GT(now.spilled_images, 0) << "after frame " << i;
        }
        EXPECT_TRUE(std::filesystem::is_empty(dir)) << "a file appeared in the folder";
      }
      fusion.Finish();
      placements = fusion.Placements();
      *stats = fusion.stats();
    }
    return placements;
  };
  // Without the optimizer (no timing dependence): the same pairs, placements and gains.
  FusionStats in_memory_stats, on_disk_stats;
  const std::vector<FramePlacement> all = run(0, false, nullptr, &in_memory_stats);
  const std::vector<FramePlacement> two = run(2, false, nullptr, &on_disk_stats);
  ASSERT_EQ(all.size(), two.size());
  for (size_t k = 0; k < all.size(); ++k) {
    EXPECT_EQ(all[k].neighbours, two[k].neighbours) << "frame " << k;
    EXPECT_EQ(all[k].mosaic_from_image, two[k].mosaic_from_image) << "frame " << k;
  }
  EXPECT_EQ(in_memory_stats.spill_reads, 0);
  EXPECT_GT(on_disk_stats.spill_reads, 0);  // Neighbours of the previous sweep, 6 frames back.
  EXPECT_TRUE(on_disk_stats.spill_error.empty()) << on_disk_stats.spill_error;
  // With the optimizer and painting: re-rendered frames read back from disk paint their own
  // values.
  CheckingSink sink;
  sink.value_of = value_of;
  FusionStats stats;
  run(2, true, &sink, &stats);
  EXPECT_EQ(wrong_bases, 0) << "of " << calls << " registrations";
  EXPECT_GT(stats.rerendered_frames, 0);
  EXPECT_GT(stats.spill_reads, on_disk_stats.spill_reads);  // Re-renders read too.
  EXPECT_EQ(sink.wrong, 0) << "of " << sink.checked << " frames painted";
  EXPECT_GE(sink.checked, 48 + stats.rerendered_frames);
  // Each frame is painted once as new; the optimizer's re-renders come as repaints (which a
  // store may write after new frames: PaintKind::kRefresh).
  EXPECT_EQ(sink.first_paints, 48);
  EXPECT_EQ(sink.repaints, stats.rerendered_frames);
  // Every frame re-rendered or deferred was a candidate of its solve; gains are not estimated
  // here, so none was for radiometry alone.
  EXPECT_GE(stats.rerender_candidates, stats.rerendered_frames + stats.deferred_rerenders);
  EXPECT_EQ(stats.radiometric_rerenders, 0);
  EXPECT_TRUE(stats.spill_error.empty()) << stats.spill_error;
  std::filesystem::remove_all(dir);
}

// The final solve's re-renders with a registration helper thread (registration_threads 2):
// the helper makes each frame's orthoimage and weights while the frame before is painted. What
// the sink gets is what the one-thread loop gives: the same repaints (origin, size, every
// sample and weight), in the same order, each followed by its frame's FramePlaced, all on the
// thread that called Finish.
TEST(MapFusionTest, FinalRerendersWithAHelperThreadPaintWhatOneThreadPaints) {
  const Sweep s = MakeSweep(36, 6, 2.0, 0.3, 31);
  // Ties with noise drawn per pair: the same whichever thread registers a pair when.
  auto registrar = [&s](const FusionFrame& base, const FusionFrame& templ) {
    return PairSeededTies(s, base, templ);
  };
  struct RepaintSeen {
    cv::Point origin;
    cv::Size size;
    double image_sum = 0, weight_sum = 0;
    int64_t placed = -1;  // The FramePlaced that followed it.
    std::thread::id thread;
  };
  struct RecordingSink : MosaicSink {
    std::mutex mu;
    bool finishing = false;
    std::vector<RepaintSeen> repaints;
    int64_t compare_at = -1;  // The repaint kept whole, to compare every sample.
    cv::Mat kept_image, kept_weight;
    void Paint(const cv::Mat&, const cv::Mat&, cv::Point) override {}
    void Repaint(const cv::Mat& image, const cv::Mat& weight, cv::Point origin) override {
      std::lock_guard<std::mutex> lock(mu);
      if (!finishing) return;
      repaints.push_back({origin, image.size(), cv::sum(image)[0], cv::sum(weight)[0], -1,
                          std::this_thread::get_id()});
      if (static_cast<int64_t>(repaints.size()) - 1 == compare_at) {
        kept_image = image.clone();
        kept_weight = weight.clone();
      }
    }
    void FramePlaced(const FramePlacement& p) override {
      std::lock_guard<std::mutex> lock(mu);
      if (finishing && !repaints.empty() && repaints.back().placed < 0) {
        repaints.back().placed = p.index;
      }
    }
  };
  auto run = [&](int threads, RecordingSink* sink, FusionStats* stats) {
    FusionOptions options;
    options.window_frames = 36;
    options.solve_every_frames = 1000;  // No background solve: Finish's is the only one.
    options.rerender_threshold_px = 0.0;
    options.compensate_gain = false;
    options.registration_threads = threads;
    MapFusion fusion(options, s.camera, registrar, sink);
    for (int64_t i = 0; i < 36; ++i) {
      FusionFrame f;
      f.index = i;
      f.time_s = static_cast<double>(i) * 0.04;
      // A ramp with the frame's own level: every sample depends on where the warp reads.
      f.image = cv::Mat(s.camera.height, s.camera.width, CV_16U);
      for (int y = 0; y < f.image.rows; ++y) {
        for (int x = 0; x < f.image.cols; ++x) {
          f.image.at<uint16_t>(y, x) = static_cast<uint16_t>(1000 + 11 * i + 3 * x + 5 * y);
        }
      }
      f.pos_mosaic_from_image = s.pos[static_cast<size_t>(i)];
      fusion.Push(std::move(f));
    }
    {
      std::lock_guard<std::mutex> lock(sink->mu);
      sink->finishing = true;
    }
    fusion.Finish();
    *stats = fusion.stats();
  };
  RecordingSink one, two;
  one.compare_at = two.compare_at = 17;
  FusionStats one_stats, two_stats;
  run(1, &one, &one_stats);
  run(2, &two, &two_stats);
  EXPECT_EQ(one_stats.rerendered_ahead, 0);
  EXPECT_GE(two_stats.rerendered_ahead, 30);  // Nearly every frame moved in the final solve.
  EXPECT_EQ(two_stats.rerendered_ahead, two_stats.rerendered_frames);
  EXPECT_EQ(one_stats.rerendered_frames, two_stats.rerendered_frames);
  ASSERT_EQ(one.repaints.size(), two.repaints.size());
  ASSERT_GE(two.repaints.size(), 30u);
  const std::thread::id caller = std::this_thread::get_id();
  for (size_t k = 0; k < one.repaints.size(); ++k) {
    const RepaintSeen &a = one.repaints[k], &b = two.repaints[k];
    EXPECT_EQ(a.origin, b.origin) << "repaint " << k;
    EXPECT_EQ(a.size, b.size) << "repaint " << k;
    EXPECT_EQ(a.image_sum, b.image_sum) << "repaint " << k;
    EXPECT_EQ(a.weight_sum, b.weight_sum) << "repaint " << k;
    EXPECT_EQ(a.placed, b.placed) << "repaint " << k;
    EXPECT_GE(b.placed, 0) << "repaint " << k << " had no FramePlaced after it";
    EXPECT_EQ(b.thread, caller) << "repaint " << k;
  }
  ASSERT_FALSE(one.kept_image.empty());
  EXPECT_EQ(cv::norm(one.kept_image, two.kept_image, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(one.kept_weight, two.kept_weight, cv::NORM_INF), 0.0);
}

// Background re-renders take what the output can absorb: while the sink reports its output
// behind by more than max_output_backlog_s, a solve paints nothing again and leaves its frames
// to the next solve; the final solve re-renders every frame that moved regardless.
TEST(MapFusionTest, BackgroundRerendersWaitWhileTheOutputIsBehind) {
  const Sweep s = MakeSweep(60, 6, 2.0, 0.3, 23);
  struct BacklogSink : MosaicSink {
    std::atomic<double> backlog_s{0.0};
    std::atomic<int> placed{0};
    void Paint(const cv::Mat&, const cv::Mat&, cv::Point) override {}
    void FramePlaced(const FramePlacement&) override { ++placed; }
    double OutputBacklogSeconds() const override { return backlog_s; }
  };
  struct Outcome {
    FusionStats before_finish, after_finish;
    int placed_before_finish = 0, placed_after_finish = 0;
  };
  auto run = [&](double sink_backlog_s, double max_backlog_s) {
    FusionOptions options;
    options.window_frames = 20;
    options.solve_every_frames = 4;
    options.rerender_threshold_px = 0.0;  // Every frame a solve moves is a re-render.
    options.compensate_gain = false;
    options.max_output_backlog_s = max_backlog_s;
    BacklogSink sink;
    sink.backlog_s = sink_backlog_s;
    MapFusion fusion(options, s.camera, IdealRegistrar(s, 0.2, 3), &sink);
    const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
    for (int64_t i = 0; i < 60; ++i) {
      FusionFrame f;
      f.index = i;
      f.time_s = static_cast<double>(i) * 0.04;
      f.image = image;
      f.pos_mosaic_from_image = s.pos[static_cast<size_t>(i)];
      fusion.Push(std::move(f));
      // Let the optimizer solve as the frames come (at most 2 s a frame on a loaded machine).
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(2);
      while (i >= 8 && i % 4 == 3 && fusion.stats().optimizer_lag_frames > 4 &&
             std::chrono::steady_clock::now() < deadline) {
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
    }
    Outcome out;
    out.before_finish = fusion.stats();
    out.placed_before_finish = sink.placed;
    fusion.Finish();
    out.after_finish = fusion.stats();
    out.placed_after_finish = sink.placed;
    return out;
  };
  const Outcome behind = run(10.0, 0.25);
  const Outcome keeping_up = run(0.0, 0.25);
  const Outcome no_bound = run(10.0, 0.0);
  std::printf(
      "behind: %lld solves, %lld re-renders, %lld deferred; keeping up: %lld solves, %lld "
      "re-renders; no bound: %lld re-renders\n",
      static_cast<long long>(behind.before_finish.solves),
      static_cast<long long>(behind.before_finish.rerendered_frames),
      static_cast<long long>(behind.before_finish.deferred_rerenders),
      static_cast<long long>(keeping_up.before_finish.solves),
      static_cast<long long>(keeping_up.before_finish.rerendered_frames),
      static_cast<long long>(no_bound.before_finish.rerendered_frames));
  for (const Outcome* o : {&behind, &keeping_up, &no_bound}) {
    ASSERT_GE(o->before_finish.solves, 3);
  }
  // Output behind: the background solves painted nothing again, and said so.
  EXPECT_EQ(behind.before_finish.rerendered_frames, 0);
  EXPECT_EQ(behind.placed_before_finish, 60);
  EXPECT_GT(behind.before_finish.deferred_rerenders, 0);
  // The final solve is not held back: every frame it moved is painted again.
  EXPECT_GT(behind.after_finish.rerendered_frames, 0);
  EXPECT_EQ(behind.placed_after_finish, 60 + behind.after_finish.rerendered_frames);
  // Output keeping up, or no bound: the background solves re-render, nothing deferred.
  for (const Outcome* o : {&keeping_up, &no_bound}) {
    EXPECT_GT(o->before_finish.rerendered_frames, 0);
    EXPECT_EQ(o->after_finish.deferred_rerenders, 0);
    EXPECT_EQ(o->placed_after_finish, 60 + o->after_finish.rerendered_frames);
  }
}

// A sink that keeps each frame's last painted placement (what the disk shows of it), with
// the output backlog it reports set by the test.
struct LastPaintSink : MosaicSink {
  std::mutex mu;
  std::map<int64_t, Eigen::Matrix3d> last;
  double backlog_s = 0.0;
  int64_t new_paints = 0;  // Paint calls (a frame's first, and what goes with the next publish).
  void Paint(const cv::Mat&, const cv::Mat&, cv::Point) override {
    std::lock_guard<std::mutex> lock(mu);
    ++new_paints;
  }
  void Repaint(const cv::Mat&, const cv::Mat&, cv::Point) override {}
  void FramePlaced(const FramePlacement& p) override {
    std::lock_guard<std::mutex> lock(mu);
    last[p.index] = p.mosaic_from_image;
  }
  double OutputBacklogSeconds() const override { return backlog_s; }
};

// Largest move of a frame's outer corners between two placements, mosaic px.
double CornerLagPx(const Eigen::Matrix3d& painted, const Eigen::Matrix3d& placed,
                   const CameraModel& camera) {
  double lag = 0.0;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(camera.width - 0.5, -0.5),
        Eigen::Vector2d(-0.5, camera.height - 0.5),
        Eigen::Vector2d(camera.width - 0.5, camera.height - 0.5)}) {
    lag = std::max(lag, (ApplyHomography(painted, c) - ApplyHomography(placed, c)).norm());
  }
  return lag;
}

// The mosaic as painted against the solution: a frame's last paint (what the disk shows)
// against its final placement. With a re-render budget too small for what each solve moves,
// frames that leave the solved window keep a lagging paint unless settled frames are
// re-rendered (FusionOptions::rerender_settled_frames); with it, every frame ends within the
// re-render threshold of where the solution puts it, also when the output is always behind
// and no background solve re-renders anything (each frame is then re-rendered as it leaves).
TEST(MapFusionTest, SettledFramesAreRepaintedWhereTheSolutionPutsThem) {
  const Sweep s = MakeSweep(200, 6, 2.0, 0.3, 29);
  struct Outcome {
    std::vector<double> lag_px;  // Per frame: largest corner move from its last paint.
    FusionStats stats;
    int64_t new_paints = 0;
  };
  auto run = [&](bool rerender_settled, double settled_threshold_px, double backlog_s = 0.0) {
    FusionOptions options;
    options.settled_rerender_threshold_px = settled_threshold_px;
    options.window_frames = 30;
    options.short_window_frames = 0;
    options.solve_every_frames = 4;
    options.max_rerenders_per_solve = 6;  // Fewer than a solve moves past the threshold.
    options.compensate_gain = false;
    options.rerender_settled_frames = rerender_settled;
    LastPaintSink sink;
    sink.backlog_s = backlog_s;
    MapFusion fusion(options, s.camera, IdealRegistrar(s, 0.2, 7), &sink);
    const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
    for (int64_t i = 0; i < 200; ++i) {
      fusion.Push(SweepFrame(s, i, image));
      // Each solve covers the same frames however fast this machine is (up to a minute each).
      const int64_t solves_due = (i + 1) / options.solve_every_frames;
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
      while (fusion.stats().solves < solves_due && std::chrono::steady_clock::now() < deadline) {
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
    }
    fusion.Finish();
    Outcome out;
    out.stats = fusion.stats();
    out.new_paints = sink.new_paints;
    for (const FramePlacement& p : fusion.Placements()) {
      out.lag_px.push_back(CornerLagPx(sink.last.at(p.index), p.mosaic_from_image, s.camera));
    }
    return out;
  };
  const Outcome without = run(false, 0.25);
  const Outcome with = run(true, 0.25);
  // Settled frames re-rendered only past 1 px: fewer of them, each frame within 1 px.
  const Outcome settled_1px = run(true, 1.0);
  const auto over = [](const Outcome& o, double px) {
    return std::count_if(o.lag_px.begin(), o.lag_px.end(), [px](double v) { return v > px; });
  };
  std::printf(
      "painted vs final: without settled re-renders mean %.3f px, max %.3f px, %ld frames over "
      "0.25 px; with them mean %.3f px, max %.3f px, %ld over 0.25 px (%lld settled re-renders, "
      "%lld frozen lagging)\n",
      Mean(without.lag_px), Max(without.lag_px), over(without, 0.25), Mean(with.lag_px),
      Max(with.lag_px), over(with, 0.25), static_cast<long long>(with.stats.settled_rerenders),
      static_cast<long long>(with.stats.settled_left_lagging));
  ASSERT_GE(with.stats.solves, 40);
  // Without: the budget leaves frames behind for good (the case this option is for).
  EXPECT_GT(over(without, 0.25), 20);
  EXPECT_EQ(without.stats.settled_rerenders, 0);
  // With: every frame within the threshold (the corner move it measures, in single
  // precision: 1e-3 px), none frozen lagging.
  EXPECT_GT(with.stats.settled_rerenders, 0);
  EXPECT_EQ(with.stats.settled_left_lagging, 0);
  EXPECT_LE(Max(with.lag_px), FusionOptions().rerender_threshold_px + 1e-3);
  std::printf("settled threshold 1 px: %lld settled re-renders, max %.3f px\n",
              static_cast<long long>(settled_1px.stats.settled_rerenders), Max(settled_1px.lag_px));
  EXPECT_LT(settled_1px.stats.settled_rerenders, with.stats.settled_rerenders);
  EXPECT_EQ(settled_1px.stats.settled_left_lagging, 0);
  EXPECT_LE(Max(settled_1px.lag_px), 1.0 + 1e-3);
  // The output always behind (10 s against max_output_backlog_s 0.25): background solves
  // re-render nothing, so each frame that leaves the held frames lagging is re-rendered then
  // (by Push), and the final solve does the rest.
  const Outcome behind_without = run(false, 0.25, 10.0);
  const Outcome behind = run(true, 0.25, 10.0);
  std::printf(
      "output behind: without settled re-renders max %.3f px, %ld frames over 0.25 px; with "
      "them max %.3f px, %lld settled re-renders, %lld of them as the frames left, %lld frozen "
      "lagging\n",
      Max(behind_without.lag_px), over(behind_without, 0.25), Max(behind.lag_px),
      static_cast<long long>(behind.stats.settled_rerenders),
      static_cast<long long>(behind.stats.settled_rerenders_on_leaving),
      static_cast<long long>(behind.stats.settled_left_lagging));
  EXPECT_GT(over(behind_without, 0.25), 100);
  EXPECT_GT(behind.stats.settled_rerenders_on_leaving, 100);
  // Those go out as new paints (their tiles with the next publish, whose resume record counts
  // the frames frozen there), not as refreshes written in slices after it: one per frame, and
  // one per frame re-rendered as it left.
  EXPECT_EQ(behind.new_paints, 200 + behind.stats.settled_rerenders_on_leaving);
  EXPECT_EQ(behind.stats.settled_left_lagging, 0);
  EXPECT_LE(Max(behind.lag_px), FusionOptions().rerender_threshold_px + 1e-3);
}

// The same with the caller running ahead of the solves, as on a loaded machine: frames join
// while a solve runs, so the oldest frames of its window leave the newest window_frames (where
// images are kept) before it moves them once more. Until session 43 such a frame lost its
// image then, the solve's budget of one re-render did not reach it, and the disk kept it where
// it was painted before (a frame 0.42-0.43 px off in each of 3 runs of this test before the fix;
// the CLI test TheStoreShowsEveryFrameWhereTheSolutionPutsIt failed once in ~50 runs). Every
// frame's last paint must be its final placement.
TEST(MapFusionTest, FramesMovedByASolveTheCallerOutranAreRepaintedThere) {
  const Sweep s = MakeSweep(320, 6, 2.0, 0.3, 31);
  FusionOptions options;
  options.window_frames = 40;
  options.short_window_frames = 0;
  options.solve_every_frames = 16;
  options.max_rerenders_per_solve = 1;  // Most moves wait for a later solve or a settled one.
  options.compensate_gain = false;
  options.rerender_settled_frames = true;
  LastPaintSink sink;
  MapFusion fusion(options, s.camera, IdealRegistrar(s, 0.2, 11), &sink);
  const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
  for (int64_t i = 0; i < 320; ++i) fusion.Push(SweepFrame(s, i, image));  // Never waiting.
  fusion.Finish();
  const FusionStats stats = fusion.stats();
  std::vector<double> lag;
  for (const FramePlacement& p : fusion.Placements()) {
    lag.push_back(CornerLagPx(sink.last.at(p.index), p.mosaic_from_image, s.camera));
  }
  const int64_t over = std::count_if(lag.begin(), lag.end(), [&](double v) {
    return v > options.settled_rerender_threshold_px + 1e-3;
  });
  std::printf(
      "caller ahead of %lld solves: painted vs final max %.3f px, %lld frames over 0.25 px "
      "(%lld settled re-renders, %lld as frames left, %lld of them painted again after a solve "
      "moved the frame)\n",
      static_cast<long long>(stats.solves), Max(lag), static_cast<long long>(over),
      static_cast<long long>(stats.settled_rerenders),
      static_cast<long long>(stats.settled_rerenders_on_leaving),
      static_cast<long long>(stats.settled_repainted_after_solve));
  ASSERT_GE(stats.solves, 10);
  EXPECT_EQ(over, 0);
  EXPECT_EQ(stats.settled_left_lagging, 0);
}

// The other race of that hand-over (session 43), made to happen on every run by the fusion's
// test seams (src/map_fusion_testing.h): a solve's snapshot holds frame F; the caller pushes
// until F leaves the fusion with its paint lagging, and Push re-renders it at the placement it
// reads then; the solve publishes F's new placement while that paint is under way (the seam in
// Push's re-render releases the held solve and waits for its publish). Push must then paint F
// again at the new placement, and its record must come last: the frame ends on disk exactly
// where the solution puts it.
struct HeldSolveRace {
  std::mutex mu;
  std::condition_variable cv;
  MapFusion* fusion = nullptr;
  bool armed = false;    // The next background solve is held at its snapshot.
  bool holding = false;  // Held now, its frames [first, last].
  bool released = false;
  int64_t first = -1, last = -1;
  int64_t straddled = -1;  // The frame whose settled paint the held solve's publish straddled.
  bool published = false;  // The held solve published before that paint's check.
};
HeldSolveRace* g_held_solve_race = nullptr;

void HoldTheArmedSolve(int64_t first, int64_t last) {
  HeldSolveRace& race = *g_held_solve_race;
  std::unique_lock<std::mutex> lock(race.mu);
  if (!race.armed) return;
  race.armed = false;
  race.holding = true;
  race.first = first;
  race.last = last;
  // Released by a settled paint of one of its frames, or given up after 60 s (the test fails).
  race.cv.wait_for(lock, std::chrono::seconds(60), [&] { return race.released; });
  race.holding = false;
}

void PublishTheHeldSolveDuringThisPaint(int64_t index) {
  HeldSolveRace& race = *g_held_solve_race;
  int64_t solves = 0;
  {
    std::lock_guard<std::mutex> lock(race.mu);
    if (!race.holding || race.released || index < race.first || index > race.last) return;
    solves = race.fusion->stats().solves;
    race.released = true;
    race.straddled = index;
  }
  race.cv.notify_all();
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (race.fusion->stats().solves == solves && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  std::lock_guard<std::mutex> lock(race.mu);
  race.published = race.fusion->stats().solves > solves;
}

TEST(MapFusionTest, ASettledPaintASolvePublishesDuringIsMadeAgainAtTheNewPlacement) {
  const Sweep s = MakeSweep(200, 6, 2.0, 0.3, 43);
  FusionOptions options;
  options.window_frames = 16;
  options.short_window_frames = 0;
  options.solve_every_frames = 4;
  options.max_rerenders_per_solve = 1;  // Leaves frames lagging as they leave.
  options.compensate_gain = false;
  options.rerender_settled_frames = true;
  LastPaintSink sink;
  MapFusion fusion(options, s.camera, IdealRegistrar(s, 0.2, 17), &sink);
  HeldSolveRace race;
  race.fusion = &fusion;
  g_held_solve_race = &race;
  struct Unset {
    ~Unset() {
      fusion_testing::SetSolveSnapshotHook(nullptr);
      fusion_testing::SetSettledPaintHook(nullptr);
    }
  } unset;
  fusion_testing::SetSolveSnapshotHook(&HoldTheArmedSolve);
  fusion_testing::SetSettledPaintHook(&PublishTheHeldSolveDuringThisPaint);
  const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
  int64_t i = 0;
  // 48 frames with the optimizer keeping up (each due solve awaited), then the next solve held
  // while the caller runs on.
  for (; i < 48; ++i) {
    const int64_t solves = fusion.stats().solves;
    const bool due = (i + 1) % options.solve_every_frames == 0;
    fusion.Push(SweepFrame(s, i, image));
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (due && fusion.stats().solves == solves && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
  }
  {
    std::lock_guard<std::mutex> lock(race.mu);
    race.armed = true;
  }
  for (; i < 200; ++i) fusion.Push(SweepFrame(s, i, image));
  fusion.Finish();
  const FusionStats stats = fusion.stats();
  std::map<int64_t, Eigen::Matrix3d> final_placement;
  for (const FramePlacement& p : fusion.Placements())
    final_placement[p.index] = p.mosaic_from_image;
  std::printf(
      "held solve of frames %lld-%lld: frame %lld's settled paint straddled its publish; %lld "
      "painted again after a solve moved the frame; that frame's last record %.2e px from its "
      "final placement\n",
      static_cast<long long>(race.first), static_cast<long long>(race.last),
      static_cast<long long>(race.straddled),
      static_cast<long long>(stats.settled_repainted_after_solve),
      race.straddled >= 0
          ? CornerLagPx(sink.last.at(race.straddled), final_placement.at(race.straddled), s.camera)
          : -1.0);
  ASSERT_GE(race.straddled, 0) << "no frame of the held solve left the fusion lagging";
  ASSERT_TRUE(race.published) << "the held solve did not publish during the paint";
  EXPECT_GE(stats.settled_repainted_after_solve, 1);
  EXPECT_LT(CornerLagPx(sink.last.at(race.straddled), final_placement.at(race.straddled), s.camera),
            1e-9);
  for (const auto& [index, placed] : final_placement) {
    EXPECT_LE(CornerLagPx(sink.last.at(index), placed, s.camera),
              options.settled_rerender_threshold_px + 1e-3)
        << "frame " << index;
  }
  EXPECT_EQ(stats.settled_left_lagging, 0);
}

// A resumed fusion takes each replayed frame as painted where the resume record says
// (FusionResumeState::painted), not at its placement: a held frame whose paint lagged when the
// record was taken is still re-rendered where the solution puts it. And a record that claims
// paints the disk never got (re-rendered tiles written after the publish carrying the record,
// lost to a kill) leaves no frame off either: with settled re-renders, the resumed fusion
// paints every held frame again after the replay (session 32).
TEST(MapFusionTest, AResumedFusionRerendersTheFramesWhosePaintLaggedAtTheRecord) {
  const Sweep s = MakeSweep(64, 6, 2.0, 0.3, 37);
  FusionOptions options;
  options.window_frames = 16;
  options.short_window_frames = 0;
  options.solve_every_frames = 4;
  options.max_rerenders_per_solve = 1;  // Leaves held frames lagging.
  options.compensate_gain = false;
  options.rerender_settled_frames = true;
  const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
  // Pushes frames [from, to) and lets the optimizer catch up after each one (a replayed frame,
  // before `live_from`, starts no solve).
  auto push = [&](MapFusion& fusion, int64_t from, int64_t to, int64_t live_from) {
    for (int64_t i = from; i < to; ++i) {
      const int64_t solves = fusion.stats().solves;
      const bool due = i >= live_from && (i + 1) % options.solve_every_frames == 0;
      fusion.Push(SweepFrame(s, i, image));
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
      while (due && fusion.stats().solves == solves &&
             std::chrono::steady_clock::now() < deadline) {
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(due ? 20 : 0));  // Its re-renders.
    }
  };
  // The killed run: 40 frames, then its record and what its sink (the disk) shows. Twice: the
  // record as written, and one whose paints never reached the disk while the record says they
  // did (the store writes re-rendered tiles in slices after the publish that carries the record,
  // so a kill in between loses them): its `painted` entries dropped.
  for (const bool claims_unwritten_paints : {false, true}) {
    LastPaintSink disk;
    FusionResumeState record;
    {
      MapFusion killed(options, s.camera, IdealRegistrar(s, 0.2, 7), &disk);
      push(killed, 0, 40, 0);
      record = killed.ResumeState(0);
    }
    ASSERT_FALSE(record.painted.empty()) << "no held frame lagged at the record";
    const size_t lagging = record.painted.size();
    if (claims_unwritten_paints) record.painted.clear();
    // The resumed run paints over the same disk.
    MapFusion resumed(options, s.camera, IdealRegistrar(s, 0.2, 7), &disk);
    const int64_t replay_from = record.ReplayFrom();
    resumed.Resume(std::move(record));
    push(resumed, replay_from, 64, 40);
    resumed.Finish();
    double worst = 0.0;
    int over = 0;
    for (const FramePlacement& p : resumed.Placements()) {
      const double lag = CornerLagPx(disk.last.at(p.index), p.mosaic_from_image, s.camera);
      worst = std::max(worst, lag);
      over += lag > options.settled_rerender_threshold_px + 1e-3 ? 1 : 0;
    }
    std::printf(
        "record with %zu held frames painted elsewhere%s; after the resume: worst %.3f px, "
        "%d frames over 0.25 px from their final placement\n",
        lagging, claims_unwritten_paints ? " but saying they are not" : "", worst, over);
    EXPECT_EQ(over, 0) << (claims_unwritten_paints ? "record claiming unwritten paints" : "");
  }
}

// A solve that runs while the producer is still painting a new frame (its Paint blocked, as
// by the store's back-pressure) must not re-render that frame first: the first paint would
// then land over the re-render while the fusion takes the frame for re-rendered. Every
// frame's first placement reported to the sink is the one Push returned.
TEST(MapFusionTest, ASolveDoesNotRerenderAFrameBeforeItsFirstPaint) {
  const Sweep s = MakeSweep(80, 6, 2.0, 0.3, 31);
  constexpr int64_t kHeld = 40;  // The frame whose first paint waits.
  struct HoldingSink : MosaicSink {
    std::mutex mu;
    std::condition_variable cv;
    const MapFusion* fusion = nullptr;
    std::thread::id producer = std::this_thread::get_id();
    bool hold_repaints = false, repaint_held = false;
    bool rerendered_held_frame = false;  // The held frame re-rendered before its first paint.
    std::map<int64_t, Eigen::Matrix3d> first;
    void Paint(const cv::Mat&, const cv::Mat&, cv::Point) override {
      std::unique_lock<std::mutex> lock(mu);
      if (!hold_repaints || !repaint_held) return;
      // The frame kHeld's first paint: let the held solve finish, and wait for the next one
      // (whose window holds this frame) to publish and re-render what it will.
      hold_repaints = false;
      cv.notify_all();
      const int64_t solves = fusion->stats().solves;
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
      while (fusion->stats().solves == solves && std::chrono::steady_clock::now() < deadline) {
        cv.wait_for(lock, std::chrono::milliseconds(2));
      }
      cv.wait_for(lock, std::chrono::seconds(2), [this] { return rerendered_held_frame; });
    }
    void Repaint(const cv::Mat&, const cv::Mat&, cv::Point) override {
      std::unique_lock<std::mutex> lock(mu);
      if (!hold_repaints) return;
      repaint_held = true;
      cv.notify_all();
      cv.wait(lock, [this] { return !hold_repaints; });
    }
    void FramePlaced(const FramePlacement& p) override {
      std::lock_guard<std::mutex> lock(mu);
      if (first.count(p.index)) return;
      first[p.index] = p.mosaic_from_image;
      if (std::this_thread::get_id() != producer) {
        rerendered_held_frame = true;
        cv.notify_all();
      }
    }
    double OutputBacklogSeconds() const override { return 0.0; }
  };
  FusionOptions options;
  options.window_frames = 30;
  options.short_window_frames = 0;
  options.solve_every_frames = 1;
  options.max_rerenders_per_solve = 0;
  options.compensate_gain = false;
  HoldingSink sink;
  MapFusion fusion(options, s.camera, IdealRegistrar(s, 0.2, 7), &sink);
  sink.fusion = &fusion;
  const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
  std::map<int64_t, Eigen::Matrix3d> pushed;
  for (int64_t i = 0; i < 80; ++i) {
    if (i == kHeld - 1) {
      std::lock_guard<std::mutex> lock(sink.mu);
      sink.hold_repaints = true;  // The solve this frame starts stops in its first re-render.
    }
    if (i == kHeld) {
      std::unique_lock<std::mutex> lock(sink.mu);
      ASSERT_TRUE(
          sink.cv.wait_for(lock, std::chrono::seconds(60), [&] { return sink.repaint_held; }))
          << "no solve re-rendered anything after frame " << kHeld - 1;
    }
    pushed[i] = fusion.Push(SweepFrame(s, i, image)).mosaic_from_image;
    if (i == kHeld) {
      ASSERT_FALSE(sink.hold_repaints) << "frame " << kHeld << " was not held";
    }
  }
  fusion.Finish();
  EXPECT_GT(fusion.stats().rerendered_frames, 0);
  ASSERT_EQ(sink.first.size(), pushed.size());
  for (const auto& [index, h] : pushed) {
    EXPECT_LT((sink.first.at(index) - h).norm(), 1e-12)
        << "frame " << index << " was first reported at a placement other than Push's";
  }
}

// A caller releases placements (ReleasePlacements, as the Mosaicker does for its frozen frames'
// file) while a background solve re-renders. The solve reads its frames' and pairs' placements
// again after its re-renders (the lag it leaves on disk), so none of them may go: here the
// caller pushes until the solve's frames have left the window and releases all it can while
// the solve is held in its first re-render. (Reading a released one was a heap use after free
// that ASan caught, sometimes, in MosaickerApiTest.)
TEST(MapFusionTest, PlacementsASolveStillReadsAreNotReleased) {
  const Sweep s = MakeSweep(90, 6, 2.0, 0.3, 37);
  struct HoldingSink : MosaicSink {
    std::mutex mu;
    std::condition_variable cv;
    std::thread::id producer = std::this_thread::get_id();
    bool holding = false, released = false, done = false;
    int64_t held_index = -1;  // The frame whose re-render is held.
    void Paint(const cv::Mat&, const cv::Mat&, cv::Point) override {}
    void FramePlaced(const FramePlacement& p) override {
      std::unique_lock<std::mutex> lock(mu);
      if (std::this_thread::get_id() == producer || done) return;
      done = true;
      held_index = p.index;
      holding = true;
      cv.notify_all();
      cv.wait_for(lock, std::chrono::seconds(60), [this] { return released; });
    }
    double OutputBacklogSeconds() const override { return 0.0; }
  };
  FusionOptions options;
  options.window_frames = 10;
  options.short_window_frames = 0;
  options.solve_every_frames = 4;
  options.rerender_threshold_px = 0.0;  // Every frame a solve moves is a re-render.
  options.max_rerenders_per_solve = 0;
  options.compensate_gain = false;
  HoldingSink sink;
  MapFusion fusion(options, s.camera, IdealRegistrar(s, 0.2, 11), &sink);
  const cv::Mat image(s.camera.height, s.camera.width, CV_16U, cv::Scalar(1000));
  int64_t next = 0;
  for (; next < 12; ++next) fusion.Push(SweepFrame(s, next, image));
  {
    std::unique_lock<std::mutex> lock(sink.mu);
    ASSERT_TRUE(sink.cv.wait_for(lock, std::chrono::seconds(60), [&] { return sink.holding; }))
        << "no background solve re-rendered a frame";
  }
  // The held solve's frames leave the window (it keeps 2 windows) and the pairs.
  for (; next < 60; ++next) fusion.Push(SweepFrame(s, next, image));
  const size_t first_held = fusion.ReleasePlacements(SIZE_MAX);
  {
    std::lock_guard<std::mutex> lock(sink.mu);
    sink.released = true;
    sink.cv.notify_all();
  }
  // Slots are push positions, and the frames were pushed from index 0: slot == index.
  EXPECT_LE(first_held, static_cast<size_t>(sink.held_index))
      << "the placement of frame " << sink.held_index
      << ", which the held solve reads again, was released";
  for (; next < 90; ++next) fusion.Push(SweepFrame(s, next, image));
  fusion.Finish();
  // Once the solve is over, what it held can go: only the window and its pairs stay.
  EXPECT_GT(fusion.ReleasePlacements(SIZE_MAX), static_cast<size_t>(sink.held_index));
  const std::vector<FramePlacement> left = fusion.Placements();
  ASSERT_FALSE(left.empty());
  EXPECT_EQ(left.back().index, 89);
}

TEST(MapFusionTest, OptionsAreValidated) {
  FusionOptions options;
  std::string error;
  EXPECT_TRUE(options.IsValid(&error));
  options.window_frames = 1;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("window_frames"), std::string::npos);
  options = FusionOptions();
  options.linear_solver = "SPARSE_SCHUR";  // Nothing to eliminate: ties join frames directly.
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("linear_solver"), std::string::npos);
  options = FusionOptions();
  options.sparse_library = "NO_SUCH_LIBRARY";
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("sparse_library"), std::string::npos);
  options.sparse_library = "ACCELERATE_SPARSE";  // A Ceres name, but Apple's only.
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("not in this build of Ceres"), std::string::npos);
  options = FusionOptions();
  options.registration_threads = 0;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("registration_threads"), std::string::npos);
  options = FusionOptions();
  options.candidate_frames = -1;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("candidate_frames"), std::string::npos);
  options = FusionOptions();
  options.images_in_memory = -1;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("images_in_memory"), std::string::npos);
  options = FusionOptions();
  options.short_window_frames = -1;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("short_window_frames"), std::string::npos);
  options = FusionOptions();
  options.settled_rerender_threshold_px = -0.5;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("settled_rerender_threshold_px"), std::string::npos);
  options = FusionOptions();
  options.full_window_every = 0;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("full_window_every"), std::string::npos);
  options = FusionOptions();
  options.solve_iterations = 0;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("solve_iterations"), std::string::npos);
  options = FusionOptions();
  options.pair_robust_scale_px = 0.0;
  EXPECT_FALSE(options.IsValid(&error));
  EXPECT_NE(error.find("pair_robust_scale_px"), std::string::npos);
}

}  // namespace
}  // namespace irmosaic
