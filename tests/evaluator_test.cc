#include "irmosaic/evaluator.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "irmosaic/error.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

namespace irmosaic {
namespace {

namespace fs = std::filesystem;

// The truth of a short simulated flight (no rendering needed).
Placements SimulatedTruth(int frames) {
  SynthOptions o;
  o.origin_lat_deg = 47.2;
  o.origin_lon_deg = 8.5;
  o.frame_count = frames;
  FlightSimulator sim(o);
  Placements truth;
  truth.origin_lat_deg = 47.2;
  truth.origin_lon_deg = 8.5;
  truth.gsd_m = sim.grid().gsd_m;
  for (int i = 0; i < frames; ++i)
    truth.frames.push_back({i, i / 25.0, sim.TrueMosaicFromImage(i)});
  return truth;
}

// The same placements expressed on another grid (origin, GSD), shifted there by `shift_px`.
Placements Regrid(const Placements& truth, double lat, double lon, double gsd,
                  const Eigen::Vector2d& shift_px) {
  const LocalFrame from(truth.origin_lat_deg, truth.origin_lon_deg), to(lat, lon);
  PlaneToGeographic from_to_geo(from);
  const MosaicGrid from_grid{truth.gsd_m}, to_grid{gsd};
  Placements run = truth;
  run.origin_lat_deg = lat;
  run.origin_lon_deg = lon;
  run.gsd_m = gsd;
  for (Placement& f : run.frames) {
    std::vector<Eigen::Vector2d> img, mos;
    for (int j = 0; j <= 8; ++j) {
      for (int i = 0; i <= 8; ++i) {
        const Eigen::Vector2d u(639.0 * i / 8, 511.0 * j / 8);
        const Eigen::Vector2d ll = from_to_geo.LatLonFromPlane(
            from_grid.PlaneFromPixel(ApplyHomography(f.mosaic_from_image, u)));
        img.push_back(u);
        mos.push_back(to_grid.PixelFromPlane(to.PlaneFromGeodetic(ll.x(), ll.y())) + shift_px);
      }
    }
    f.mosaic_from_image = FitHomography(img, mos);
  }
  return run;
}

TEST(Evaluator, TruthScoresZero) {
  const Placements truth = SimulatedTruth(40);
  const Evaluator ev(truth);
  const PlacementScore s = ev.ScorePlacements(truth, "truth");
  EXPECT_EQ(s.frames_scored, 40);
  EXPECT_EQ(s.frames_missing, 0);
  EXPECT_LT(s.rmse_px.max, 1e-9);
  EXPECT_LT(s.absolute_rmse_m, 1e-9);
  EXPECT_DOUBLE_EQ(s.rmse_px.share_within_1px, 1.0);
}

TEST(Evaluator, TwoPixelShiftScoresTwoPixels) {
  const Placements truth = SimulatedTruth(40);
  const Evaluator ev(truth);
  Placements run = truth;
  for (Placement& f : run.frames) {
    Eigen::Matrix3d shift = Eigen::Matrix3d::Identity();
    shift(0, 2) = 2.0;  // 2 px east.
    f.mosaic_from_image = shift * f.mosaic_from_image;
  }
  const PlacementScore s = ev.ScorePlacements(run);
  EXPECT_NEAR(s.rmse_px.mean, 2.0, 1e-6);
  EXPECT_NEAR(s.rmse_px.max, 2.0, 1e-6);
  EXPECT_NEAR(s.georeference_offset_m.x(), 2.0 * truth.gsd_m, 1e-6);
  EXPECT_NEAR(s.georeference_offset_m.y(), 0.0, 1e-6);
  EXPECT_NEAR(s.relative_rmse_px, 0.0, 1e-6);
  EXPECT_DOUBLE_EQ(s.rmse_px.share_within_1px, 0.0);
}

// A run's grid has its own origin (its first POS record, with errors) and GSD: the evaluator
// converts through geodesy, so a 2 px shift on a 0.3 m grid reads 2 * 0.3 / gsd_truth px.
TEST(Evaluator, ShiftOnAnotherGridIsConvertedThroughGeodesy) {
  const Placements truth = SimulatedTruth(40);
  const Evaluator ev(truth);
  // 1.5 km and 0.9 km away from the truth's origin.
  const double lat = 47.2 + 0.008, lon = 8.5 - 0.02;
  const PlacementScore same = ev.ScorePlacements(Regrid(truth, lat, lon, 0.3, {0, 0}));
  EXPECT_LT(same.rmse_px.max, 0.01);  // The regridding itself (homography fit) is exact enough.
  const PlacementScore shifted = ev.ScorePlacements(Regrid(truth, lat, lon, 0.3, {0, 2}));
  const double expected = 2.0 * 0.3 / truth.gsd_m;
  EXPECT_NEAR(shifted.rmse_px.mean, expected, 0.01);
  EXPECT_NEAR(shifted.rmse_px.max, expected, 0.02);
  // 2 px south on the run's grid: a georeference offset of 0.6 m south.
  EXPECT_NEAR(shifted.georeference_offset_m.y(), -0.6, 0.005);
  EXPECT_NEAR(shifted.absolute_rmse_m, 0.6, 0.005);
}

TEST(Evaluator, MissingFramesAreCounted) {
  const Placements truth = SimulatedTruth(20);
  Placements run = truth;
  run.frames.resize(15);
  run.frames[3].mosaic_from_image(0, 0) = std::nan("");
  const PlacementScore s = Evaluator(truth).ScorePlacements(run);
  EXPECT_EQ(s.frames_scored, 14);
  EXPECT_EQ(s.frames_missing, 6);
}

TEST(Evaluator, PairsScoredInTheOverlap) {
  const Placements truth = SimulatedTruth(20);
  const Evaluator ev(truth);
  std::vector<PairHomography> pairs;
  for (int i = 0; i + 1 < 8; ++i) {
    PairHomography p;
    p.base = i;
    p.template_index = i + 1;
    Eigen::Matrix3d shift = Eigen::Matrix3d::Identity();
    shift(1, 2) = 2.0;  // 2 px down in the base image.
    p.base_from_template =
        shift * truth.frames[i].mosaic_from_image.inverse() * truth.frames[i + 1].mosaic_from_image;
    pairs.push_back(p);
  }
  pairs.push_back({0, 12, Eigen::Matrix3d::Identity()});  // No overlap: not scored.
  pairs.push_back({0, 99, Eigen::Matrix3d::Identity()});  // Not in the truth.
  const PairsScore s = ev.ScorePairs(pairs);
  EXPECT_EQ(s.pairs_given, 9);
  EXPECT_EQ(s.pairs_scored, 7);
  EXPECT_NEAR(s.rmse_px.mean, 2.0, 1e-6);
  for (const PairScore& p : s.pairs) EXPECT_GE(p.points, 4);
}

TEST(Evaluator, FilesRoundTripAndPlot) {
  const Placements truth = SimulatedTruth(30);
  const fs::path dir = fs::temp_directory_path() / ("irmosaic_eval_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  truth.SaveJson((dir / "truth.json").string());
  const Placements back = Placements::LoadJson((dir / "truth.json").string());
  ASSERT_EQ(back.frames.size(), truth.frames.size());
  EXPECT_EQ(back.frames[7].mosaic_from_image, truth.frames[7].mosaic_from_image);  // Exact.
  EXPECT_EQ(back.origin_lat_deg, truth.origin_lat_deg);
  const PlacementScore s = Evaluator(truth).ScorePlacements(back, "reloaded");
  EXPECT_EQ(s.rmse_px.max, 0.0);
  PlotRmseVsIndex({s}, (dir / "plot.png").string());
  EXPECT_GT(fs::file_size(dir / "plot.png"), 1000u);
  std::ofstream((dir / "bad.json").string()) << R"({"origin": {"lat_deg": 1}, "gsd_m": 1})";
  EXPECT_THROW(Placements::LoadJson((dir / "bad.json").string()), InputError);
  fs::remove_all(dir);
}

TEST(Evaluator, Statistics) {
  const ErrorStats s = ComputeErrorStats({0.5, 1.0, 2.0, 4.0});
  EXPECT_DOUBLE_EQ(s.mean, 1.875);
  EXPECT_DOUBLE_EQ(s.median, 1.5);
  EXPECT_DOUBLE_EQ(s.max, 4.0);
  EXPECT_DOUBLE_EQ(s.share_within_1px, 0.5);
  EXPECT_NEAR(s.p95, 2.0 + 0.85 * 2.0, 1e-12);
}

// The worst frames of a score: the largest RMSE first, ties by index, at most n.
TEST(Evaluator, WorstFramesAreTheLargestRmseFirst) {
  PlacementScore score;
  const double rmse[] = {0.4, 7.5, 0.9, 7.5, 120.0, 0.1, 3.0};
  for (int i = 0; i < 7; ++i) score.frames.push_back({10 + i, rmse[i]});
  const std::vector<FrameScore> worst = WorstFrames(score, 4);
  ASSERT_EQ(worst.size(), 4u);
  EXPECT_EQ(worst[0].index, 14);  // 120 px.
  EXPECT_EQ(worst[1].index, 11);  // 7.5 px, the lower index of the tie first.
  EXPECT_EQ(worst[2].index, 13);
  EXPECT_EQ(worst[3].index, 16);  // 3 px.
  EXPECT_EQ(WorstFrames(score, 50).size(), 7u);
  EXPECT_TRUE(WorstFrames(PlacementScore{}).empty());
}

}  // namespace
}  // namespace irmosaic

namespace irmosaic {
namespace {

// End to end through the command line: `synth` renders the bundled sample, `eval` scores the
// POS-only placements and the truth itself.
TEST(EvaluatorCli, SynthThenEvalOnTheBundledSample) {
  const fs::path dir = fs::temp_directory_path() / ("irmosaic_cli_" + std::to_string(::getpid()));
  const std::string cli = testing::CliPath();
  const std::string synth = cli + " synth --config " +
                            testing::SamplePath("sample_flight/flight.json") +
                            " --frames 16 --out " + dir.string() + " 2>/dev/null";
  ASSERT_EQ(std::system(synth.c_str()), 0) << synth;
  for (const char* name :
       {"frames/000015.tif", "frames.csv", "pos.csv", "camera.json", "truth.json", "pos_only.json",
        "flight.json", "true_pos.csv", "truth_pairs.json"}) {
    EXPECT_TRUE(fs::exists(dir / name)) << name;
  }
  const Placements truth = Placements::LoadJson((dir / "truth.json").string());
  ASSERT_EQ(truth.frames.size(), 16u);
  EXPECT_EQ(truth.image_width, 640);
  EXPECT_EQ(truth.image_height, 512);
  // The written truth is the simulator's, and flight.json renders the same flight again.
  FlightSimulator again(SynthOptions::LoadJson((dir / "flight.json").string()));
  EXPECT_EQ(truth.frames[9].mosaic_from_image, again.TrueMosaicFromImage(9));
  const std::string eval = cli + " eval --truth " + (dir / "truth.json").string() + " " +
                           (dir / "truth.json").string() + " " + (dir / "pos_only.json").string() +
                           " --json " + (dir / "eval.json").string() + " --plot " +
                           (dir / "eval.png").string() + " > " + (dir / "eval.txt").string();
  ASSERT_EQ(std::system(eval.c_str()), 0) << eval;
  std::ifstream in(dir / "eval.json");
  const nlohmann::json scores = nlohmann::json::parse(in);
  // The printed worst frames of the POS-only run: its highest per-frame RMSE first.
  int worst_index = -1;
  double worst_rmse = -1.0;
  for (const auto& f : scores["runs"][1]["frames"]) {
    if (f["rmse_px"].get<double>() > worst_rmse) {
      worst_rmse = f["rmse_px"].get<double>();
      worst_index = f["index"].get<int>();
    }
  }
  std::ifstream text(dir / "eval.txt");
  std::vector<std::string> lines;
  for (std::string line; std::getline(text, line);) lines.push_back(line);
  ASSERT_EQ(lines.size(), 4u);  // Per run: the scores, then the worst frames.
  char expected[64];
  std::snprintf(expected, sizeof(expected), "  worst frames (index: RMSE px): %d: %.3f,",
                worst_index, worst_rmse);
  EXPECT_EQ(lines[3].rfind(expected, 0), 0u) << lines[3] << " / expected " << expected;
  EXPECT_EQ(std::count(lines[3].begin(), lines[3].end(), ','), 4);  // Five frames.
  EXPECT_EQ(lines[1].rfind("  worst frames (index: RMSE px): 0: 0.000,", 0), 0u) << lines[1];
  EXPECT_EQ(scores["runs"][0]["rmse_px"]["max"].get<double>(), 0.0);
  // POS errors of 2 m and 0.3 degree at 600 m: the POS-only placement is metres off.
  EXPECT_GT(scores["runs"][1]["rmse_m"]["median"].get<double>(), 1.0);
  EXPECT_EQ(scores["runs"][1]["frames_scored"].get<int>(), 16);
  EXPECT_TRUE(fs::exists(dir / "eval.png"));
  // The truth's pairs score 0 against the truth: 7 along each of 2 sweeps, 8 between them.
  const std::vector<PairHomography> pairs = LoadPairsJson((dir / "truth_pairs.json").string());
  EXPECT_EQ(pairs.size(), 22u);
  const PairsScore ps = Evaluator(truth).ScorePairs(pairs);
  EXPECT_EQ(ps.pairs_scored, 22);
  EXPECT_LT(ps.rmse_px.max, 1e-6);
  fs::remove_all(dir);
}

}  // namespace
}  // namespace irmosaic

namespace irmosaic {
namespace {

TEST(EvaluatorInput, NumberBeyondDoubleIsAnInputErrorNotACrash) {
  const auto path = std::filesystem::temp_directory_path() /
                    ("irmosaic_eval_huge_" + std::to_string(::getpid()) + ".json");
  std::ofstream(path)
      << R"({"origin": {"lat_deg": 1e999, "lon_deg": 8}, "gsd_m": 0.5, "frames": []})";
  EXPECT_THROW(Placements::LoadJson(path.string()), InputError);
  EXPECT_THROW(SynthOptions::FromJson(R"({"seed": 1e999})", "flight.json"), InputError);
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace irmosaic
