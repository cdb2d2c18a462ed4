// Map fusion at flight length (paper Fig. 10): placement RMSE against frame index with and
// without the global optimization, mapping latency per frame while the optimizer runs, and the
// optimizer's time per window. Registration is the ideal registrar of tests/fusion_sweep.h
// (true tie points + Gaussian noise), so the figures isolate the fusion.
// Usage: fusion_bench [--frames N] [--rate FPS] [--json FILE] [--plot FILE.png] [--render 0|1]
//   [--precision 0|1] [--solver NAME] [--sparse NAME] [--window N] [--solve-every N]
//   [--short-window N] [--full-every N] [--iterations N]
//   [--max-ties N] [--neighbours N] [--tie-noise PX] [--tie-sigma PX] [--seed N]
//   [--skip-without 0|1]
// Latency is per Push(): wall time and the calling thread's CPU time (less inflated by a
// loaded machine).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>

#include "../tests/fusion_sweep.h"
#include "irmosaic/evaluator.h"

using namespace irmosaic;
using Clock = std::chrono::steady_clock;

struct Result {
  std::vector<double> rmse, seam, latency_ms, latency_cpu_ms, relative, lag_frames;
  std::vector<Eigen::Vector2d> centre_error;  // Placement minus truth at the image centre.
  FusionStats stats;
};

double g_tie_noise_px = 0.15;

// Discards what it is given: the latency then includes orthorectification, gain and
// feathering, but not a store.
class NullSink : public MosaicSink {
 public:
  void Paint(const cv::Mat&, const cv::Mat&, cv::Point) override {}
  void FramePlaced(const FramePlacement&) override {}
};

double ThreadCpuMs() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

Result Run(const testing::Sweep& s, FusionOptions options, bool optimize, double rate_fps) {
  options.optimize = optimize;
  NullSink sink;
  MapFusion fusion(options, s.camera, testing::IdealRegistrar(s, g_tie_noise_px, 11),
                   options.render ? &sink : nullptr);
  cv::Mat image(s.camera.height, s.camera.width, CV_16U);
  cv::randu(image, 1000, 3000);
  Result r;
  const auto start = Clock::now();
  for (size_t i = 0; i < s.pos.size(); ++i) {
    FusionFrame f;
    f.index = static_cast<int64_t>(i);
    f.time_s = i / 25.0;
    f.image = image;
    f.pos_mosaic_from_image = s.pos[i];
    f.prior_sqrt_information = s.prior[i];
    const auto t0 = Clock::now();
    const double cpu0 = ThreadCpuMs();
    fusion.Push(std::move(f));
    r.latency_cpu_ms.push_back(ThreadCpuMs() - cpu0);
    r.latency_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
    r.lag_frames.push_back(static_cast<double>(fusion.stats().optimizer_lag_frames));
    std::this_thread::sleep_until(
        start + std::chrono::microseconds(static_cast<int64_t>(1e6 * (i + 1) / rate_fps)));
  }
  fusion.Finish();
  const auto placements = fusion.Placements();
  for (const FramePlacement& p : placements) {
    r.rmse.push_back(testing::PlacementRmse(p.mosaic_from_image, s.truth[p.index], s.camera));
    const Eigen::Vector2d c((s.camera.width - 1) / 2.0, (s.camera.height - 1) / 2.0);
    r.centre_error.push_back(ApplyHomography(p.mosaic_from_image, c) -
                             ApplyHomography(s.truth[p.index], c));
  }
  for (size_t j = 1; j < placements.size(); ++j) {
    r.seam.push_back(testing::SeamRmse(placements, s, static_cast<int64_t>(j) - 1, j));
  }
  r.relative = testing::RelativeRmse(placements, s);
  r.stats = fusion.stats();
  return r;
}

double Percentile(std::vector<double> v, double q) {
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(q * v.size()))];
}
double Mean(const std::vector<double>& v) {
  double sum = 0;
  for (double x : v) sum += x;
  return sum / v.size();
}

int main(int argc, char** argv) {
  int frames = 2000;
  double rate = 100.0;
  std::string json_path, plot_path;
  uint32_t seed = 7;
  bool skip_without = false;
  FusionOptions options;
  options.solve_every_frames = 25;
  options.render = false;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--frames") frames = std::stoi(argv[i + 1]);
    if (a == "--rate") rate = std::stod(argv[i + 1]);
    if (a == "--json") json_path = argv[i + 1];
    if (a == "--plot") plot_path = argv[i + 1];
    if (a == "--render") options.render = std::stoi(argv[i + 1]) != 0;
    if (a == "--precision") options.estimate_precision = std::stoi(argv[i + 1]) != 0;
    if (a == "--solver") options.linear_solver = argv[i + 1];
    if (a == "--sparse") options.sparse_library = argv[i + 1];
    if (a == "--tie-sigma") options.tie_sigma_px = std::stod(argv[i + 1]);
    if (a == "--neighbours") options.max_neighbours = std::stoi(argv[i + 1]);
    if (a == "--tie-noise") g_tie_noise_px = std::stod(argv[i + 1]);
    if (a == "--seed") seed = static_cast<uint32_t>(std::stoul(argv[i + 1]));
    if (a == "--window") options.window_frames = std::stoi(argv[i + 1]);
    if (a == "--short-window") options.short_window_frames = std::stoi(argv[i + 1]);
    if (a == "--full-every") options.full_window_every = std::stoi(argv[i + 1]);
    if (a == "--solve-every") options.solve_every_frames = std::stoi(argv[i + 1]);
    if (a == "--iterations") options.solve_iterations = std::stoi(argv[i + 1]);
    if (a == "--max-ties") options.max_ties_per_pair = std::stoi(argv[i + 1]);
    if (a == "--skip-without") skip_without = std::stoi(argv[i + 1]) != 0;
  }
  const testing::Sweep s = testing::MakeSweep(frames, 6, 2.0, 0.3, seed);
  std::vector<double> pos_rmse;
  for (int i = 0; i < frames; ++i)
    pos_rmse.push_back(testing::PlacementRmse(s.pos[i], s.truth[i], s.camera));
  {
    // Is the POS prior consistent with the POS errors? Whitened chi^2 of the truth's corners
    // and centre against the POS placement (expected about 6: six pose errors).
    double chi2 = 0.0;
    for (int i = 0; i < frames; ++i) {
      const std::array<Eigen::Vector2d, 5> pts = {
          Eigen::Vector2d(0, 0), Eigen::Vector2d(s.camera.width - 1, 0),
          Eigen::Vector2d(s.camera.width - 1, s.camera.height - 1),
          Eigen::Vector2d(0, s.camera.height - 1),
          Eigen::Vector2d((s.camera.width - 1) / 2.0, (s.camera.height - 1) / 2.0)};
      Eigen::Matrix<double, 10, 1> e;
      for (int k = 0; k < 5; ++k)
        e.segment<2>(2 * k) =
            ApplyHomography(s.truth[i], pts[k]) - ApplyHomography(s.pos[i], pts[k]);
      chi2 += (s.prior[i] * e).squaredNorm();
    }
    std::printf("POS prior: mean whitened chi^2 of the truth %.2f (10 points)\n", chi2 / frames);
  }
  const Result with = Run(s, options, true, rate);
  const Result without = skip_without ? with : Run(s, options, false, rate);
  std::printf("%-22s %9s %9s %9s %9s %10s %10s %10s %10s\n", "run", "mean_px", "p95_px", "max_px",
              "seam_px", "lat_p50ms", "lat_p99ms", "cpu_p50ms", "cpu_p99ms");
  auto row = [&](const char* name, const Result& r) {
    std::printf("%-22s %9.3f %9.3f %9.3f %9.3f %10.3f %10.3f %10.3f %10.3f\n", name, Mean(r.rmse),
                Percentile(r.rmse, 0.95), Percentile(r.rmse, 1.0), Mean(r.seam),
                Percentile(r.latency_ms, 0.5), Percentile(r.latency_ms, 0.99),
                Percentile(r.latency_cpu_ms, 0.5), Percentile(r.latency_cpu_ms, 0.99));
  };
  std::printf("%-22s %10.3f %10.3f %10.3f\n", "POS only", Mean(pos_rmse),
              Percentile(pos_rmse, 0.95), Percentile(pos_rmse, 1.0));
  row("with optimization", with);
  row("without optimization", without);
  std::printf(
      "optimizer: %lld solves, mean %.0f ms, max %.0f ms per window, lag at the end %lld frames\n",
      static_cast<long long>(with.stats.solves),
      with.stats.solves ? with.stats.total_solve_ms / with.stats.solves : 0.0,
      with.stats.max_solve_ms, static_cast<long long>(with.stats.optimizer_lag_frames));
  std::printf("optimizer CPU time per window: mean %.0f ms, max %.0f ms\n",
              with.stats.solves ? with.stats.total_solve_cpu_ms / with.stats.solves : 0.0,
              with.stats.max_solve_cpu_ms);
  std::printf("optimizer lag behind the foreground: p50 %.0f, p99 %.0f, max %.0f frames\n",
              Percentile(with.lag_frames, 0.5), Percentile(with.lag_frames, 0.99),
              Percentile(with.lag_frames, 1.0));
  if (with.stats.predicted_rmse_px > 0.0) {
    std::printf("predicted RMS placement error of the final solve (covariance): %.3f px\n",
                with.stats.predicted_rmse_px);
  }
  // Where the error lives: the mean centre error of blocks of 120 frames (20 sweeps) is the
  // low-frequency part (gauge, drift); what is left after removing it is local.
  {
    double low = 0.0, local = 0.0;
    int n = 0;
    for (size_t b = 0; b + 120 <= with.centre_error.size(); b += 120) {
      Eigen::Vector2d mean = Eigen::Vector2d::Zero();
      for (size_t i = b; i < b + 120; ++i) mean += with.centre_error[i] / 120.0;
      std::printf("block %4zu: mean centre error (%6.3f, %6.3f) px\n", b, mean.x(), mean.y());
      for (size_t i = b; i < b + 120; ++i) {
        low += mean.squaredNorm();
        local += (with.centre_error[i] - mean).squaredNorm();
        ++n;
      }
    }
    std::printf("relative (global similarity removed): mean %.3f max %.3f px\n",
                Mean(with.relative), Percentile(with.relative, 1.0));
    if (n > 0) {
      std::printf("centre error RMS: low-frequency (120-frame blocks) %.3f px, local %.3f px\n",
                  std::sqrt(low / n), std::sqrt(local / n));
    }
  }
  if (!plot_path.empty()) {
    std::vector<PlacementScore> scores(3);
    const std::vector<const std::vector<double>*> series = {&with.rmse, &without.rmse, &pos_rmse};
    const char* names[] = {"with global optimization", "without (real-time mapping only)",
                           "POS only"};
    for (int k = 0; k < 3; ++k) {
      scores[k].name = names[k];
      scores[k].rmse_px = ComputeErrorStats(*series[k]);
      scores[k].frames_scored = static_cast<int>(series[k]->size());
      for (size_t i = 0; i < series[k]->size(); ++i) {
        FrameScore f;
        f.index = static_cast<int>(i);
        f.rmse_px = (*series[k])[i];
        scores[k].frames.push_back(f);
      }
    }
    PlotRmseVsIndex(scores, plot_path, "Placement RMSE vs frame index (ideal registrar)");
  }
  if (!json_path.empty()) {
    nlohmann::json doc = {
        {"benchmark", "fusion"},
        {"frames", frames},
        {"rate_fps", rate},
        {"render", options.render},
        {"linear_solver", options.linear_solver},
        {"sparse_library", options.sparse_library},
        {"pos_only", {{"mean_px", Mean(pos_rmse)}, {"max_px", Percentile(pos_rmse, 1.0)}}},
        {"with_optimization",
         {{"mean_px", Mean(with.rmse)},
          {"p95_px", Percentile(with.rmse, 0.95)},
          {"max_px", Percentile(with.rmse, 1.0)},
          {"seam_mean_px", Mean(with.seam)},
          {"latency_p50_ms", Percentile(with.latency_ms, 0.5)},
          {"latency_p99_ms", Percentile(with.latency_ms, 0.99)},
          {"latency_cpu_p50_ms", Percentile(with.latency_cpu_ms, 0.5)},
          {"latency_cpu_p99_ms", Percentile(with.latency_cpu_ms, 0.99)},
          {"lag_p50_frames", Percentile(with.lag_frames, 0.5)},
          {"lag_max_frames", Percentile(with.lag_frames, 1.0)},
          {"predicted_rmse_px", with.stats.predicted_rmse_px},
          {"mean_solve_ms",
           with.stats.solves ? with.stats.total_solve_ms / with.stats.solves : 0.0},
          {"mean_solve_cpu_ms",
           with.stats.solves ? with.stats.total_solve_cpu_ms / with.stats.solves : 0.0},
          {"max_solve_cpu_ms", with.stats.max_solve_cpu_ms},
          {"solves", with.stats.solves},
          {"max_solve_ms", with.stats.max_solve_ms},
          {"rmse_px", with.rmse}}},
        {"without_optimization",
         {{"mean_px", Mean(without.rmse)},
          {"max_px", Percentile(without.rmse, 1.0)},
          {"seam_mean_px", Mean(without.seam)},
          {"rmse_px", without.rmse}}}};
    std::ofstream(json_path) << doc.dump(1) << "\n";
  }
  return 0;
}
