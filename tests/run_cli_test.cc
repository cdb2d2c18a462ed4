// `irmosaic run` end to end on a simulated flight, checked with real clients (GDAL) against the
// simulator's truth: georeference, pixel values, existing-store refusal, kill -9 and --resume.
#include <gdal_priv.h>
#include <gtest/gtest.h>
#include <ogr_spatialref.h>
#include <ogrsf_frmts.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "frames_gpkg_lock.h"
#include "irmosaic/evaluator.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

namespace irmosaic {
namespace {
namespace fs = std::filesystem;

// A small simulated flight, written once for all tests of this file.
class RunCliTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    GDALAllRegister();
    dir_ =
        (fs::temp_directory_path() / ("irmosaic_run_cli_" + std::to_string(::getpid()))).string();
    fs::remove_all(dir_);
    WriteFlight(dir_ + "/flight", 0.0, 0.0);  // POS exact: the mosaic must sit where the truth is.
  }
  // dir_ is removed with the program's other scratch files after a passing run, and kept after
  // a failure (tests/support/temp_cleanup.cc).

  // The test flight with the POS errors given (1 sigma) into `path`.
  static void WriteFlight(const std::string& path, double position_sigma_m,
                          double attitude_sigma_deg) {
    SynthOptions options;
    options.ground_path = testing::SamplePath("sample_flight/ground_naip_2019.tif");
    options.seed = 5;
    options.frame_count = 64;
    options.altitude_m = 600;
    options.heading_deg = 80;
    options.frames_per_sweep = 8;
    options.position_sigma_m = position_sigma_m;
    options.attitude_sigma_deg = attitude_sigma_deg;
    options.sensor.gain_drift = false;
    options.sensor.noise_psnr_db = 35.0;
    FlightSimulator sim(options);
    sim.WriteFlight(path);
  }

  // Runs the CLI on `flight` (the test flight by default) with `extra` arguments; returns its
  // exit code, stderr in *log.
  static int RunCli(const std::string& store, const std::string& extra, std::string* log,
                    std::string flight = "") {
    if (flight.empty()) flight = dir_ + "/flight";
    const std::string log_path = store + ".log";
    const std::string command = testing::CliPath() + " run --frames " + flight +
                                "/frames.csv --pos " + flight + "/pos.csv --camera " + flight +
                                "/camera.json --out " + store + " " + extra + " > /dev/null 2> " +
                                log_path;
    const int status = std::system(command.c_str());
    std::ifstream in(log_path);
    log->assign(std::istreambuf_iterator<char>(in), {});
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }

  // Starts `irmosaic run` on `flight` (the test flight by default) into `store` as a child
  // process (stderr to `log_path`, discarded by default) with `extra` arguments, for a test to
  // kill or wait for; returns its pid.
  static pid_t StartRun(const std::string& store, const std::vector<std::string>& extra,
                        std::string flight = "", const std::string& log_path = "/dev/null") {
    if (flight.empty()) flight = dir_ + "/flight";
    std::vector<std::string> args = {"irmosaic", "run",
                                     "--frames", flight + "/frames.csv",
                                     "--pos",    flight + "/pos.csv",
                                     "--camera", flight + "/camera.json",
                                     "--out",    store};
    args.insert(args.end(), extra.begin(), extra.end());
    std::vector<char*> argv;
    for (std::string& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    const pid_t child = fork();
    if (child == 0) {
      std::freopen(log_path.c_str(), "w", stderr);
      execv(testing::CliPath().c_str(), argv.data());
      _exit(127);
    }
    return child;
  }
  // The same with `--window window` when window > 0.
  static pid_t StartRun(const std::string& store, int window) {
    return StartRun(store, window > 0 ? std::vector<std::string>{"--window", std::to_string(window)}
                                      : std::vector<std::string>{});
  }

  // The last frame the store's published state holds, or `otherwise` (no manifest yet, or
  // one being replaced).
  static int64_t PublishedLastIndex(const std::string& store, int64_t otherwise) {
    std::ifstream in(store + "/manifest.json");
    if (!in) return otherwise;
    const nlohmann::json m = nlohmann::json::parse(in, nullptr, false);
    if (m.is_object() && m.contains("application") && m["application"].is_object() &&
        m["application"].contains("last_index")) {
      return m["application"]["last_index"].get<int64_t>();
    }
    return otherwise;
  }

  // Waits (up to 2 minutes) until the store's published state is past frame `index`, then
  // kills `child` with SIGKILL; returns the last frame published then.
  static int64_t KillAfterPublished(pid_t child, const std::string& store, int64_t index) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
    int64_t last_index = -1;
    while (std::chrono::steady_clock::now() < deadline) {
      last_index = PublishedLastIndex(store, last_index);
      if (last_index >= index) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    kill(child, SIGKILL);
    int status = 0;
    waitpid(child, &status, 0);
    return last_index;
  }

  // Per frame: the largest corner distance (px) between its footprint in frames.gpkg and its
  // final placement.
  static std::vector<double> FootprintLagPx(const std::string& store, std::string placed_in = "") {
    if (placed_in.empty()) placed_in = store;
    const Placements run = Placements::LoadJson(placed_in + "/placements.json");
    std::map<int64_t, Eigen::Matrix3d> placed;
    for (const Placement& p : run.frames) placed[p.index] = p.mosaic_from_image;
    GDALDatasetUniquePtr gpkg(
        GDALDataset::Open((store + "/frames.gpkg").c_str(), GDAL_OF_VECTOR | GDAL_OF_READONLY));
    std::vector<double> lag;
    if (!gpkg || !gpkg->GetLayerByName("frames")) return lag;
    const std::array<Eigen::Vector2d, 4> corners = {
        Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(639.5, -0.5), Eigen::Vector2d(639.5, 511.5),
        Eigen::Vector2d(-0.5, 511.5)};
    for (auto& feature : *gpkg->GetLayerByName("frames")) {
      const Eigen::Matrix3d& h = placed.at(feature->GetFieldAsInteger64("frame_index"));
      const OGRLinearRing* ring = feature->GetGeometryRef()->toPolygon()->getExteriorRing();
      double worst = 0.0;
      for (int c = 0; c < 4; ++c) {
        const Eigen::Vector3d q = h * corners[c].homogeneous();
        const Eigen::Vector2d solution_m(q.x() / q.z() * run.gsd_m, -q.y() / q.z() * run.gsd_m);
        worst = std::max(
            worst, (Eigen::Vector2d(ring->getX(c), ring->getY(c)) - solution_m).norm() / run.gsd_m);
      }
      lag.push_back(worst);
    }
    return lag;
  }

  // Pixels of the store's first overview (mosaic.vrt's overview 1) that differ from the mean of
  // the four level-0 pixels below them by more than `tolerance` counts, where all five are
  // covered: an overview behind level 0. Returns -1 if the store has no overview.
  static int64_t StaleOverviewPixels(const std::string& store, double tolerance = 8.0) {
    GDALDatasetUniquePtr vrt(GDALDataset::Open((store + "/mosaic.vrt").c_str(), GDAL_OF_RASTER));
    if (!vrt || vrt->GetRasterBand(1)->GetOverviewCount() < 1) return -1;
    const int w = vrt->GetRasterXSize(), h = vrt->GetRasterYSize();
    cv::Mat value(h, w, CV_32F), alpha(h, w, CV_32F);
    GDALRasterBand* v1 = vrt->GetRasterBand(1)->GetOverview(0);
    GDALRasterBand* a1 = vrt->GetRasterBand(2)->GetOverview(0);
    cv::Mat value1(v1->GetYSize(), v1->GetXSize(), CV_32F), alpha1(value1.size(), CV_32F);
    if (vrt->GetRasterBand(1)->RasterIO(GF_Read, 0, 0, w, h, value.data, w, h, GDT_Float32, 0, 0) !=
            CE_None ||
        vrt->GetRasterBand(2)->RasterIO(GF_Read, 0, 0, w, h, alpha.data, w, h, GDT_Float32, 0, 0) !=
            CE_None ||
        v1->RasterIO(GF_Read, 0, 0, value1.cols, value1.rows, value1.data, value1.cols, value1.rows,
                     GDT_Float32, 0, 0) != CE_None ||
        a1->RasterIO(GF_Read, 0, 0, value1.cols, value1.rows, alpha1.data, value1.cols, value1.rows,
                     GDT_Float32, 0, 0) != CE_None) {
      return -1;
    }
    double alpha_max = 0.0;
    cv::minMaxLoc(alpha, nullptr, &alpha_max);
    int64_t stale = 0;
    for (int r = 0; r < value1.rows && 2 * r + 1 < h; ++r) {
      for (int c = 0; c < value1.cols && 2 * c + 1 < w; ++c) {
        if (alpha1.at<float>(r, c) < alpha_max) continue;
        double sum = 0.0;
        bool covered = true;
        for (int k = 0; k < 4; ++k) {
          covered = covered && alpha.at<float>(2 * r + k / 2, 2 * c + k % 2) >= alpha_max;
          sum += value.at<float>(2 * r + k / 2, 2 * c + k % 2);
        }
        if (covered && std::abs(sum / 4.0 - value1.at<float>(r, c)) > tolerance) ++stale;
      }
    }
    return stale;
  }

  static std::string dir_;
};
std::string RunCliTest::dir_;

TEST_F(RunCliTest, MosaicIsGeoreferencedWhereTheTruthIs) {
  const std::string store = dir_ + "/a.irmosaic";
  std::string log;
  ASSERT_EQ(RunCli(store, "", &log), 0) << log;
  // GDAL reads the live index; its CRS is the ortho plane at the run's origin.
  GDALDatasetUniquePtr vrt(GDALDataset::Open((store + "/mosaic.vrt").c_str(), GDAL_OF_RASTER));
  ASSERT_TRUE(vrt) << CPLGetLastErrorMsg();
  const Placements run = Placements::LoadJson(store + "/placements.json");
  const Placements truth = Placements::LoadJson(dir_ + "/flight/truth.json");
  OGRSpatialReference expected, actual;
  expected.importFromWkt(LocalFrame(run.origin_lat_deg, run.origin_lon_deg).CrsWkt().c_str());
  actual.importFromWkt(vrt->GetProjectionRef());
  EXPECT_TRUE(actual.IsSame(&expected)) << vrt->GetProjectionRef();
  // Placement against the truth, in truth pixels (the GSD): within one pixel.
  const PlacementScore score = Evaluator(truth).ScorePlacements(run, "run");
  std::printf("placement vs truth: mean %.3f px, max %.3f px over %d frames\n", score.rmse_px.mean,
              score.rmse_px.max, score.frames_scored);
  EXPECT_EQ(score.frames_scored, 64);
  EXPECT_LT(score.rmse_px.mean, 1.0);
  EXPECT_LT(score.rmse_px.max, 2.0);
  // Pixel values: the mosaic at each frame's centre (read through the VRT's geotransform)
  // equals the frame's own centre value within the noise.
  double gt[6];
  ASSERT_EQ(vrt->GetGeoTransform(gt), CE_None);
  std::vector<double> diffs;
  for (const Placement& p : run.frames) {
    const Eigen::Vector3d c = p.mosaic_from_image * Eigen::Vector3d(319.5, 255.5, 1.0);
    const double x_m = c.x() / c.z() * run.gsd_m, y_m = -c.y() / c.z() * run.gsd_m;
    const int col = static_cast<int>(std::floor((x_m - gt[0]) / gt[1]));
    const int row = static_cast<int>(std::floor((y_m - gt[3]) / gt[5]));
    uint16_t mosaic[9];
    ASSERT_EQ(vrt->GetRasterBand(1)->RasterIO(GF_Read, col - 1, row - 1, 3, 3, mosaic, 3, 3,
                                              GDT_UInt16, 0, 0),
              CE_None);
    char name[32];
    std::snprintf(name, sizeof(name), "/flight/frames/%06d.tif", p.index);
    GDALDatasetUniquePtr frame(GDALDataset::Open((dir_ + name).c_str(), GDAL_OF_RASTER));
    ASSERT_TRUE(frame) << name;
    uint16_t own[9];
    ASSERT_EQ(
        frame->GetRasterBand(1)->RasterIO(GF_Read, 318, 254, 3, 3, own, 3, 3, GDT_UInt16, 0, 0),
        CE_None);
    double a = 0, b = 0;
    for (int k = 0; k < 9; ++k) {
      a += mosaic[k] / 9.0;
      b += own[k] / 9.0;
    }
    diffs.push_back(std::abs(a - b));
  }
  std::sort(diffs.begin(), diffs.end());
  // PSNR 35 dB of 65535: noise sigma ~1170 counts; a 3x3 mean ~390. Blending and gain
  // compensation move values by a few hundred counts more.
  std::printf("centre value difference: median %.0f, p90 %.0f counts\n", diffs[diffs.size() / 2],
              diffs[diffs.size() * 9 / 10]);
  EXPECT_LT(diffs[diffs.size() / 2], 1500.0);
}

// The store records where each frame is painted (frames.gpkg: footprints, rewritten at each
// re-render). `irmosaic run` re-renders the frames that left the optimization window where the
// solution put them, so with a short window every footprint is the solution's
// (placements.json) within the re-render threshold, 0.25 px; without (--no-settled-rerenders)
// frames keep earlier placements on disk.
TEST_F(RunCliTest, TheStoreShowsEveryFrameWhereTheSolutionPutsIt) {
  // POS errors as in the tests (2 m, 0.3 deg): solves move frames by pixels.
  const std::string flight = dir_ + "/pos_error_flight";
  WriteFlight(flight, 2.0, 0.3);
  std::string log;
  const std::string exact = dir_ + "/settled.irmosaic", lagging = dir_ + "/unsettled.irmosaic";
  // One re-render per background solve: the solves alone leave frames lagging.
  const std::string options =
      "--window 16 --short-window 0 --max-rerenders 1 --pos-sigma 2 --att-sigma 0.3";
  ASSERT_EQ(RunCli(exact, options, &log, flight), 0) << log;
  ASSERT_EQ(RunCli(lagging, options + " --no-settled-rerenders", &log, flight), 0) << log;
  const std::vector<double> on = FootprintLagPx(exact), off = FootprintLagPx(lagging);
  ASSERT_EQ(on.size(), 64u);
  ASSERT_EQ(off.size(), 64u);
  const auto over = [](const std::vector<double>& v) {
    return std::count_if(v.begin(), v.end(), [](double x) { return x > 0.25 + 1e-3; });
  };
  std::printf(
      "footprint on disk vs final placement: max %.3f px (%ld frames over 0.25 px); with "
      "--no-settled-rerenders max %.3f px (%ld over)\n",
      *std::max_element(on.begin(), on.end()), over(on), *std::max_element(off.begin(), off.end()),
      over(off));
  EXPECT_EQ(over(on), 0);
  EXPECT_GT(over(off), 0);
  // The run's report counts them: settled frames re-rendered, none left lagging.
  std::ifstream report(exact + "/run_report.json");
  const nlohmann::json doc = nlohmann::json::parse(report);
  EXPECT_GT(doc["optimizer"]["settled_rerenders"].get<int64_t>(), 0);
  EXPECT_EQ(doc["optimizer"]["settled_left_lagging"].get<int64_t>(), 0);
}

TEST_F(RunCliTest, ExistingStoreIsRefusedWithoutResumeOrOverwrite) {
  const std::string store = dir_ + "/b.irmosaic";
  fs::create_directories(store);
  std::ofstream(store + "/manifest.json") << "{}";
  std::string log;
  EXPECT_NE(RunCli(store, "", &log), 0);
  EXPECT_NE(log.find("--resume"), std::string::npos) << log;
  EXPECT_NE(log.find("--overwrite"), std::string::npos) << log;
  EXPECT_TRUE(fs::exists(store + "/manifest.json"));  // Nothing destroyed.
}

TEST_F(RunCliTest, KillNineThenResumeMatchesAnUninterruptedRun) {
  const std::string reference = dir_ + "/ref.irmosaic";
  std::string log;
  ASSERT_EQ(RunCli(reference, "", &log), 0) << log;
  const std::string store = dir_ + "/killed.irmosaic";
  const pid_t child = StartRun(store, 0);
  // Kill mid-run, once a quarter of the flight (frames 0-15) is published. (Until session 15
  // this waited for generation 8; a faster pipeline finishes the 64 frames in fewer
  // publishes, every 0.25 s, so the count was never reached.)
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  int64_t last_index = -1;
  bool ended_by_itself = false;
  int status = 0;
  while (std::chrono::steady_clock::now() < deadline) {
    last_index = PublishedLastIndex(store, last_index);
    if (last_index >= 15) break;
    if (waitpid(child, &status, WNOHANG) == child) {
      ended_by_itself = true;
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (!ended_by_itself) {
    kill(child, SIGKILL);
    waitpid(child, &status, 0);
  }
  ASSERT_FALSE(ended_by_itself) << "the run ended before it was killed";
  ASSERT_GE(last_index, 15) << "the run published too little before the deadline";
  ASSERT_LT(last_index, 63) << "the run had published the whole flight: not a mid-run kill";
  std::printf("killed with frames 0-%lld published\n", static_cast<long long>(last_index));
  // The killed store loads in GDAL.
  {
    GDALDatasetUniquePtr vrt(GDALDataset::Open((store + "/mosaic.vrt").c_str(), GDAL_OF_RASTER));
    ASSERT_TRUE(vrt) << CPLGetLastErrorMsg();
    // Every pixel reads without error.
    std::vector<uint16_t> all(static_cast<size_t>(vrt->GetRasterXSize()) * vrt->GetRasterYSize());
    EXPECT_EQ(vrt->GetRasterBand(1)->RasterIO(
                  GF_Read, 0, 0, vrt->GetRasterXSize(), vrt->GetRasterYSize(), all.data(),
                  vrt->GetRasterXSize(), vrt->GetRasterYSize(), GDT_UInt16, 0, 0),
              CE_None)
        << CPLGetLastErrorMsg();
  }
  ASSERT_EQ(RunCli(store, "--resume", &log), 0) << log;
  EXPECT_NE(log.find("resuming after frame"), std::string::npos) << log;
  // Frames placed after the resume agree with the uninterrupted run within 0.5 px.
  const Placements ref = Placements::LoadJson(reference + "/placements.json");
  const Placements resumed = Placements::LoadJson(store + "/placements.json");
  const PlacementScore score = Evaluator(ref).ScorePlacements(resumed, "resumed");
  std::printf("resumed vs uninterrupted: %d frames, mean %.3f px, max %.3f px\n",
              score.frames_scored, score.rmse_px.mean, score.rmse_px.max);
  EXPECT_GT(score.frames_scored, 0);
  EXPECT_LT(score.rmse_px.max, 0.5);
  GDALDatasetUniquePtr vrt(GDALDataset::Open((store + "/mosaic.vrt").c_str(), GDAL_OF_RASTER));
  ASSERT_TRUE(vrt);
  GDALDatasetUniquePtr ref_vrt(
      GDALDataset::Open((reference + "/mosaic.vrt").c_str(), GDAL_OF_RASTER));
  // The resumed mosaic covers the whole flight, as the uninterrupted one does.
  EXPECT_NEAR(vrt->GetRasterXSize(), ref_vrt->GetRasterXSize(), 2);
  EXPECT_NEAR(vrt->GetRasterYSize(), ref_vrt->GetRasterYSize(), 2);
}

// A flight longer than the optimization window (--window 16, 64 frames): frames that left the
// window before the kill were frozen at their published placement, so the resume must start from
// the placements the store recorded, not re-derive them. Killed once the published state is past
// two windows; the resumed placements.json must hold every frame and agree with an uninterrupted
// run with the same options within the 0.5 px (worst grid point of any frame).
TEST_F(RunCliTest, KillNineThenResumeWithAShortWindowMatchesAnUninterruptedRun) {
  const std::string reference = dir_ + "/ref16.irmosaic";
  std::string log;
  ASSERT_EQ(RunCli(reference, "--window 16", &log), 0) << log;
  const std::string store = dir_ + "/killed16.irmosaic";
  // Kill once the published state is past frame 32 (two windows frozen behind it).
  const int64_t last_index = KillAfterPublished(StartRun(store, 16), store, 32);
  ASSERT_GE(last_index, 32) << "the run published too little before the deadline";
  std::printf("killed with frames 0-%lld published\n", static_cast<long long>(last_index));
  ASSERT_EQ(RunCli(store, "--resume --window 16", &log), 0) << log;
  EXPECT_NE(log.find("resuming after frame"), std::string::npos) << log;
  const Placements ref = Placements::LoadJson(reference + "/placements.json");
  const Placements resumed = Placements::LoadJson(store + "/placements.json");
  const PlacementScore score = Evaluator(ref).ScorePlacements(resumed, "resumed");
  double worst_px = 0.0;
  for (const FrameScore& f : score.frames) worst_px = std::max(worst_px, f.max_px);
  std::printf(
      "resumed (--window 16) vs uninterrupted: %d of %d frames, %d missing, worst %.3f px"
      " (RMSE mean %.3f, max %.3f px)\n",
      score.frames_scored, score.frames_in_truth, score.frames_missing, worst_px,
      score.rmse_px.mean, score.rmse_px.max);
  EXPECT_EQ(score.frames_in_truth, 64);
  EXPECT_EQ(score.frames_missing, 0);
  EXPECT_EQ(resumed.frames.size(), ref.frames.size());
  EXPECT_LT(worst_px, 0.5);
}

// The store after kill -9 and --resume shows every frame where the resumed run's solution puts
// it: a record for each of the 64 frames in frames.gpkg, each footprint within the re-render
// threshold (0.25 px) of the frame's final placement, frozen frames (left the window before the
// kill) included. POS errors as in the tests so that solves move frames by pixels;
// one re-render per solve so that frames leave the window lagging.
TEST_F(RunCliTest, KillNineThenResumeLeavesEveryFrameOnDiskWhereTheSolutionPutsIt) {
  const std::string flight = dir_ + "/pos_error_flight";
  if (!fs::exists(flight + "/truth.json")) WriteFlight(flight, 2.0, 0.3);
  const std::vector<std::string> options = {"--window",    "16", "--max-rerenders", "1",
                                            "--pos-sigma", "2",  "--att-sigma",     "0.3"};
  const std::string store = dir_ + "/killed_settled.irmosaic";
  const int64_t last_index = KillAfterPublished(StartRun(store, options, flight), store, 32);
  ASSERT_GE(last_index, 32) << "the run published too little before the deadline";
  ASSERT_LT(last_index, 63) << "the run had published the whole flight: not a mid-run kill";
  std::string joined;
  for (const std::string& o : options) joined += " " + o;
  std::string log;
  ASSERT_EQ(RunCli(store, "--resume" + joined, &log, flight), 0) << log;
  const std::vector<double> lag = FootprintLagPx(store);
  const long over = std::count_if(lag.begin(), lag.end(), [](double x) { return x > 0.25 + 1e-3; });
  std::printf(
      "killed with frames 0-%lld published; after --resume: %zu records, max %.3f px from "
      "the final placement, %ld over 0.25 px\n",
      static_cast<long long>(last_index), lag.size(),
      lag.empty() ? 0.0 : *std::max_element(lag.begin(), lag.end()), over);
  EXPECT_EQ(lag.size(), 64u);
  EXPECT_EQ(over, 0);
  // The overviews show what level 0 shows (before session 32 the resume left those the kill
  // caught between two overview updates behind, for good).
  const int64_t stale = StaleOverviewPixels(store);
  std::printf("overview pixels differing from level 0 by more than 8 counts: %lld\n",
              static_cast<long long>(stale));
  EXPECT_EQ(stale, 0);
}

// Another program holding frames.gpkg's write lock from the store's first moment to past the
// run's end (a script's transaction, a GIS editing the footprints): the live publishes go on
// without frames.gpkg (the records wait in manifest.json), the closing one gives up after its
// 10 s wait and `run` exits 1 with the error and its fix, but only after writing placements.json
// and run_report.json (before session 46 it wrote neither). Once the lock is gone, `--resume`
// puts every footprint in frames.gpkg.
TEST_F(RunCliTest, AFramesGpkgLockedPastTheEndStillGetsPlacementsAndReportAndResumeCompletes) {
  const std::string store = dir_ + "/locked.irmosaic";
  const std::string gpkg = store + "/frames.gpkg";
  int go[2], told[2];
  ASSERT_EQ(pipe(go), 0);
  ASSERT_EQ(pipe(told), 0);
  // The lock holder: waits for frames.gpkg (the store creates it with its first frame), takes
  // its write lock with a transaction holding a write, says 'h', holds it until `go` says
  // anything (or closes), rolls back and says 'r'. 'x' if it could not lock within 120 s.
  const pid_t holder = fork();
  if (holder == 0) {
    close(go[1]);
    close(told[0]);
    CPLPushErrorHandler(CPLQuietErrorHandler);
    GDALDataset* ds = nullptr;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
    while (std::chrono::steady_clock::now() < deadline) {
      if (fs::exists(gpkg) && (ds = testing::LockFramesGpkg(gpkg)) != nullptr) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    char said = ds != nullptr ? 'h' : 'x';
    if (write(told[1], &said, 1) != 1 || ds == nullptr) _exit(3);
    char byte = 0;
    (void)!read(go[0], &byte, 1);
    testing::UnlockFramesGpkg(ds);
    said = 'r';
    _exit(write(told[1], &said, 1) == 1 ? 0 : 4);
  }
  close(go[0]);
  close(told[1]);
  const std::string log_path = store + ".log";
  const pid_t run = StartRun(store, {}, "", log_path);
  char said = 0;
  const bool locked = read(told[0], &said, 1) == 1 && said == 'h';
  // The run, under the lock to its end: its closing wait is 10 s.
  int status = -1;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(300);
  while (waitpid(run, &status, WNOHANG) == 0) {
    if (std::chrono::steady_clock::now() > deadline) {
      kill(run, SIGKILL);
      waitpid(run, &status, 0);
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::string log;
  {
    std::ifstream in(log_path);
    log.assign(std::istreambuf_iterator<char>(in), {});
  }
  // What frames.gpkg held while locked (the holder's transaction writes nothing to read).
  int64_t in_gpkg_while_locked = -1;
  {
    GDALDatasetUniquePtr ds(GDALDataset::Open(gpkg.c_str(), GDAL_OF_VECTOR | GDAL_OF_READONLY));
    if (ds && ds->GetLayerByName("frames")) {
      in_gpkg_while_locked = ds->GetLayerByName("frames")->GetFeatureCount();
    }
  }
  const char byte = 'g';
  const bool released = write(go[1], &byte, 1) == 1 && read(told[0], &said, 1) == 1 && said == 'r';
  close(go[1]);
  close(told[0]);
  int holder_status = 0;
  waitpid(holder, &holder_status, 0);
  ASSERT_TRUE(locked) << "the second process could not lock " << gpkg;
  ASSERT_TRUE(released);
  ASSERT_TRUE(WIFEXITED(status)) << "the run did not end within 300 s: " << log;
  EXPECT_EQ(WEXITSTATUS(status), 1) << log;
  EXPECT_NE(log.find("irmosaic run: error:"), std::string::npos) << log;
  EXPECT_NE(log.find("frames.gpkg"), std::string::npos) << log;
  EXPECT_NE(log.find("--resume"), std::string::npos) << log;
  // The lock held back the footprints, not the mosaic: every frame placed and in the manifest.
  const nlohmann::json manifest = nlohmann::json::parse(std::ifstream(store + "/manifest.json"));
  const size_t pending = manifest["frames"]["pending"].size();
  std::printf("under the lock: %lld records in frames.gpkg, %zu pending in manifest.json\n",
              static_cast<long long>(in_gpkg_while_locked), pending);
  EXPECT_GE(pending, 1u);
  EXPECT_EQ(in_gpkg_while_locked + static_cast<int64_t>(pending), 64);
  // The placements and the report, written in spite of the failed close.
  ASSERT_TRUE(fs::exists(store + "/placements.json")) << log;
  EXPECT_EQ(Placements::LoadJson(store + "/placements.json").frames.size(), 64u);
  ASSERT_TRUE(fs::exists(store + "/run_report.json")) << log;
  const nlohmann::json report = nlohmann::json::parse(std::ifstream(store + "/run_report.json"));
  EXPECT_EQ(report["frames_placed"], 64);
  EXPECT_GE(report["frames_gpkg_locked"].get<int64_t>(), 1);
  ASSERT_TRUE(report["finish_error"].is_string()) << report.dump(2);
  EXPECT_NE(report["finish_error"].get<std::string>().find("frames.gpkg"), std::string::npos);

  // The lock gone, a resume completes the store: every footprint in frames.gpkg.
  ASSERT_EQ(RunCli(store, "--resume", &log), 0) << log;
  const std::vector<double> lag = FootprintLagPx(store);
  EXPECT_EQ(lag.size(), 64u);
  EXPECT_LE(lag.empty() ? 1e9 : *std::max_element(lag.begin(), lag.end()), 0.25 + 1e-3);
  const nlohmann::json resumed = nlohmann::json::parse(std::ifstream(store + "/run_report.json"));
  EXPECT_TRUE(resumed["finish_error"].is_null()) << resumed.dump(2);
}

// Bad video input through the whole command: the flight's frames as an MJPEG AVI (8-bit), one
// frame zeroed mid-stream and the file cut before its end. The run goes on past the damaged
// frame with a warning naming it, stops at the cut with a warning, and the frames after the
// damaged one keep their times (a one-frame shift would move them by a frame spacing).
TEST_F(RunCliTest, DamagedVideoSkipsTheBadFrameWarnsOfTheCutAndKeepsTimes) {
  const std::string video = dir_ + "/flight.avi";
  {
    cv::VideoWriter writer(video, cv::VideoWriter::fourcc('M', 'J', 'P', 'G'), 25.0,
                           cv::Size(640, 512), false);
    ASSERT_TRUE(writer.isOpened());
    for (int i = 0; i < 64; ++i) {
      char name[32];
      std::snprintf(name, sizeof(name), "/flight/frames/%06d.tif", i);
      const cv::Mat frame16 = cv::imread(dir_ + name, cv::IMREAD_UNCHANGED);
      ASSERT_FALSE(frame16.empty()) << name;
      cv::Mat frame8;
      frame16.convertTo(frame8, CV_8U, 1.0 / 256.0);
      writer.write(frame8);
    }
  }
  std::ifstream in(video, std::ios::binary);
  std::string avi((std::istreambuf_iterator<char>(in)), {});
  in.close();
  std::vector<size_t> starts;  // Frame JPEGs: '00dc' chunks starting with FF D8.
  for (size_t at = avi.find("00dc"); at != std::string::npos; at = avi.find("00dc", at + 4)) {
    if (at + 10 <= avi.size() && avi.compare(at + 8, 2, "\xff\xd8") == 0) starts.push_back(at + 8);
  }
  ASSERT_EQ(starts.size(), 64u);
  std::fill(avi.begin() + static_cast<std::ptrdiff_t>(starts[20]),
            avi.begin() + static_cast<std::ptrdiff_t>(starts[21]) - 8, '\0');
  std::ofstream(dir_ + "/damaged.avi", std::ios::binary) << avi.substr(0, starts[48] + 100);

  const Placements truth = Placements::LoadJson(dir_ + "/flight/truth.json");
  const std::string t0 = std::to_string(truth.frames.front().time_s);
  const std::string store = dir_ + "/video.irmosaic";
  const std::string log_path = store + ".log";
  const std::string command = testing::CliPath() + " run --frames " + dir_ +
                              "/damaged.avi --fps 25 --t0 " + t0 + " --pos " + dir_ +
                              "/flight/pos.csv --camera " + dir_ + "/flight/camera.json --out " +
                              store + " > /dev/null 2> " + log_path;
  const int status = std::system(command.c_str());
  std::ifstream log_in(log_path);
  const std::string log((std::istreambuf_iterator<char>(log_in)), {});
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << log;
  EXPECT_NE(log.find("warning: skipped cannot decode " + dir_ + "/damaged.avi frame 20"),
            std::string::npos)
      << log;
  EXPECT_NE(log.find("damaged.avi ends after 48 frames but its header announces 64"),
            std::string::npos)
      << log;
  const Placements run = Placements::LoadJson(store + "/placements.json");
  std::set<int> placed;
  for (const Placement& p : run.frames) placed.insert(p.index);
  EXPECT_EQ(placed.count(20), 0u);
  EXPECT_EQ(placed.count(21), 1u);
  EXPECT_EQ(placed.count(48), 0u);
  EXPECT_GE(placed.size(), 40u);
  // Placement against the truth (POS exact): frames after the damaged one are where they belong.
  // A frame given its neighbour's time and POS would be off by a frame spacing (hundreds of
  // pixels); 8-bit JPEG frames register a little worse than the 16-bit TIFFs (measured: mean
  // 1.06 px, max 2.14 px), so 5 px tells the two apart with room.
  const PlacementScore score = Evaluator(truth).ScorePlacements(run, "video");
  std::printf("damaged video vs truth: %d frames, mean %.3f px, max %.3f px\n", score.frames_scored,
              score.rmse_px.mean, score.rmse_px.max);
  EXPECT_LT(score.rmse_px.mean, 2.0);
  EXPECT_LT(score.rmse_px.max, 5.0);

  // A video with no frame at all: refused before anything is written, naming the file.
  std::ofstream(dir_ + "/empty.avi", std::ios::binary) << avi.substr(0, starts[0] - 8);
  std::string empty_log;
  const std::string empty_store = dir_ + "/empty.irmosaic";
  const std::string empty_command = testing::CliPath() + " run --frames " + dir_ +
                                    "/empty.avi --pos " + dir_ + "/flight/pos.csv --camera " +
                                    dir_ + "/flight/camera.json --out " + empty_store +
                                    " > /dev/null 2> " + empty_store + ".log";
  const int empty_status = std::system(empty_command.c_str());
  std::ifstream empty_in(empty_store + ".log");
  empty_log.assign(std::istreambuf_iterator<char>(empty_in), {});
  EXPECT_TRUE(WIFEXITED(empty_status) && WEXITSTATUS(empty_status) != 0) << empty_log;
  EXPECT_NE(empty_log.find("empty.avi"), std::string::npos) << empty_log;
  EXPECT_NE(empty_log.find("no frame that can be decoded"), std::string::npos) << empty_log;
  EXPECT_FALSE(fs::exists(empty_store));  // Nothing written.
}

}  // namespace
}  // namespace irmosaic
