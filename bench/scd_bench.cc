// SCD coarse matching against cv::matchTemplate (TM_CCOEFF_NORMED) and cv::phaseCorrelate:
// success rate (error < 1 px) and ms per 640x512 pair over noise and blur, one core.
//
//   scd_bench [--json FILE] [--pairs N] [--psnr 35,30,25,20] [--blur 1,2,3,4] [--radius 64]
//             [--methods scd,tm,pc] [--seed 1]
//             SCD options (library defaults when absent): [--sigma S] [--floor K]
//             [--flat zero|mask|soft] [--criterion sig|scd] [--subpixel parabola|gauss]
//             [--subpixel_step H] [--min_ratio R] [--pyramid F] [--coarse_sigma S]
//             [--weight_cap C] [--template_step 1|2]
//
// Pairs: real thermal frames (shared/data/thermal) warped by an oblique homography onto a
// 1150x760 "ortho" canvas (irregular valid area), two 640x512 crops with 15-25 % valid overlap
// cut from it (the template's canvas moved by a random sub-pixel shift), random warped-frame
// footprints as masks, template gain 0.7-1.4 and offset +-20 % of range, pose error uniform in
// +-60 px per axis, search radius 64 px. Per condition, in the camera frame before the warp:
// Gaussian blur of the template frame, white noise on both frames at the given PSNR (8-bit
// range). Same pairs and noise for every method.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "irmosaic/scd.h"
#include "test_data.h"

namespace {

using irmosaic::ScdMatcher;
using irmosaic::ScdOptions;
using irmosaic::ScdResult;

// A pair before degradation: one real frame, two crops of its oblique "ortho" warp.
struct Scene {
  cv::Mat frame;        // CV_32F
  Eigen::Vector2d sub;  // template canvas moved by this sub-pixel shift
  cv::Rect a, b;        // base and template crops of the canvas
  cv::Mat base_footprint, templ_footprint;
  double gain = 1.0, offset = 0.0;
  Eigen::Vector2d truth, predicted;
  double overlap = 0.0;
};

struct Pair {
  cv::Mat base, base_mask, templ, templ_mask;  // CV_32F images, CV_8U masks
  Eigen::Vector2d truth, predicted;
};

std::vector<double> ParseList(const std::string& s) {
  std::vector<double> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) out.push_back(std::stod(item));
  return out;
}

cv::Mat RandomFootprint(cv::Size size, std::mt19937* rng) {
  std::uniform_real_distribution<double> inset(0.0, 0.15);
  const double w = size.width, h = size.height;
  std::vector<cv::Point> quad = {{int(inset(*rng) * w), int(inset(*rng) * h)},
                                 {int((1 - inset(*rng)) * w), int(inset(*rng) * h)},
                                 {int((1 - inset(*rng)) * w), int((1 - inset(*rng)) * h)},
                                 {int(inset(*rng) * w), int((1 - inset(*rng)) * h)}};
  cv::Mat mask = cv::Mat::zeros(size, CV_8U);
  cv::fillConvexPoly(mask, quad, cv::Scalar(255));
  return mask;
}

double ValidOverlap(const cv::Mat& base_mask, const cv::Mat& templ_mask, cv::Point offset) {
  const cv::Rect in_t = cv::Rect(0, 0, templ_mask.cols, templ_mask.rows) &
                        cv::Rect(-offset.x, -offset.y, base_mask.cols, base_mask.rows);
  if (in_t.empty()) return 0.0;
  cv::Mat both;
  cv::bitwise_and(templ_mask(in_t), base_mask(in_t + offset), both);
  return cv::countNonZero(both) / double(std::max(1, cv::countNonZero(templ_mask)));
}

const cv::Size kCanvas(1150, 760), kCrop(640, 512);

cv::Mat OrthoFromImage() {
  const std::vector<cv::Point2f> src = {{0, 0}, {640, 0}, {640, 512}, {0, 512}};
  const std::vector<cv::Point2f> dst = {{0, 0}, {1150, 0}, {950, 760}, {200, 760}};
  return cv::getPerspectiveTransform(src, dst);
}

// Frame `image` warped to the canvas (moved by `sub`), and its validity.
void Warp(const cv::Mat& image, const Eigen::Vector2d& sub, cv::Mat* ortho, cv::Mat* mask) {
  const cv::Mat shift = (cv::Mat_<double>(3, 3) << 1, 0, sub.x(), 0, 1, sub.y(), 0, 0, 1);
  const cv::Mat h = shift * OrthoFromImage();
  cv::warpPerspective(image, *ortho, h, kCanvas, cv::INTER_LINEAR);
  cv::warpPerspective(cv::Mat(image.size(), CV_8U, cv::Scalar(255)), *mask, h, kCanvas,
                      cv::INTER_NEAREST);
}

std::vector<Scene> MakeScenes(int count, unsigned seed) {
  std::vector<std::string> files;
  for (const char* dir : {"thermal/seq_1_60_30", "thermal/seq_0_100_90"}) {
    for (const auto& e :
         std::filesystem::directory_iterator(irmosaic::testing::SharedDataPath(dir))) {
      if (e.path().extension() == ".jpg") files.push_back(e.path().string());
    }
  }
  std::sort(files.begin(), files.end());
  std::mt19937 rng(seed);
  std::shuffle(files.begin(), files.end(), rng);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  std::vector<Scene> scenes;
  for (int i = 0; i < count; ++i) {
    Scene s;
    cv::imread(files[i % files.size()], cv::IMREAD_GRAYSCALE).convertTo(s.frame, CV_32F);
    // One draw a statement, y first: a call's argument order is unspecified, and every
    // compiler must draw the same scenes.
    const double sub_y = uni(rng) - 0.5;
    s.sub = Eigen::Vector2d(uni(rng) - 0.5, sub_y);
    cv::Mat ortho, mb, mt;
    Warp(s.frame, Eigen::Vector2d::Zero(), &ortho, &mb);
    Warp(s.frame, s.sub, &ortho, &mt);
    for (int attempt = 0; attempt < 5000; ++attempt) {
      const int ay = int(uni(rng) * (kCanvas.height - kCrop.height));
      s.a = cv::Rect(cv::Point(int(uni(rng) * (kCanvas.width - kCrop.width)), ay), kCrop);
      const int by = int(uni(rng) * (kCanvas.height - kCrop.height));
      s.b = cv::Rect(cv::Point(int(uni(rng) * (kCanvas.width - kCrop.width)), by), kCrop);
      s.base_footprint = RandomFootprint(kCrop, &rng);
      s.templ_footprint = RandomFootprint(kCrop, &rng);
      s.overlap = ValidOverlap(mb(s.a) & s.base_footprint, mt(s.b) & s.templ_footprint,
                               s.b.tl() - s.a.tl());
      if (s.overlap >= 0.15 && s.overlap <= 0.25) break;
    }
    s.gain = 0.7 + 0.7 * uni(rng);
    s.offset = (uni(rng) - 0.5) * 0.4 * 255.0;
    s.truth = Eigen::Vector2d(s.b.x - s.a.x, s.b.y - s.a.y) - s.sub;
    const double predicted_y = 120.0 * (uni(rng) - 0.5);
    s.predicted = s.truth + Eigen::Vector2d(120.0 * (uni(rng) - 0.5), predicted_y);
    scenes.push_back(std::move(s));
  }
  return scenes;
}

// Degradation in the camera frame (as a sensor makes it): the template frame blurred by
// blur_sigma, white noise at psnr_db (8-bit range) on both frames, template gain and offset;
// then both warped to the canvas and cropped; no data = 0.
Pair Render(const Scene& s, double psnr_db, double blur_sigma, unsigned seed) {
  cv::RNG rng(seed);
  const double noise_std = 255.0 / std::pow(10.0, psnr_db / 20.0);
  cv::Mat noise(s.frame.size(), CV_32F), fb, ft;
  rng.fill(noise, cv::RNG::NORMAL, 0.0, noise_std);
  fb = s.frame + noise;
  if (blur_sigma > 0) {
    cv::GaussianBlur(s.frame, ft, cv::Size(), blur_sigma);
  } else {
    ft = s.frame.clone();
  }
  rng.fill(noise, cv::RNG::NORMAL, 0.0, noise_std);
  ft = (ft + noise) * s.gain + s.offset;
  Pair p;
  cv::Mat ortho, mask;
  Warp(fb, Eigen::Vector2d::Zero(), &ortho, &mask);
  p.base = ortho(s.a).clone();
  p.base_mask = mask(s.a) & s.base_footprint;
  Warp(ft, s.sub, &ortho, &mask);
  p.templ = ortho(s.b).clone();
  p.templ_mask = mask(s.b) & s.templ_footprint;
  p.base.setTo(0.0f, ~p.base_mask);
  p.templ.setTo(0.0f, ~p.templ_mask);
  p.truth = s.truth;
  p.predicted = s.predicted;
  return p;
}

double ParabolaDelta(double l, double c, double r) {
  const double curv = l - 2 * c + r;
  return curv < 0 ? std::clamp(0.5 * (l - r) / curv, -0.5, 0.5) : 0.0;
}

// No-data filled with the mean of the valid pixels, so that the baselines (which take no
// masks here) do not lock onto the edges of the valid areas.
cv::Mat FillNoData(const cv::Mat& image, const cv::Mat& mask) {
  cv::Mat out = image.clone();
  out.setTo(cv::mean(image, mask), ~mask);
  return out;
}

// TM_CCOEFF_NORMED of the template part that can overlap, over the same search window
// (no-data mean-filled; filling included in its time).
Eigen::Vector2d MatchTemplateCcoeff(const Pair& in, double radius) {
  Pair p = in;
  p.base = FillNoData(in.base, in.base_mask);
  p.templ = FillNoData(in.templ, in.templ_mask);
  const int u0 = int(std::ceil(p.predicted.x() - radius)),
            u1 = int(std::floor(p.predicted.x() + radius));
  const int v0 = int(std::ceil(p.predicted.y() - radius)),
            v1 = int(std::floor(p.predicted.y() + radius));
  const cv::Rect t_roi(cv::Point(std::max(0, -u1), std::max(0, -v1)),
                       cv::Point(std::min(p.templ.cols, p.base.cols - u0),
                                 std::min(p.templ.rows, p.base.rows - v0)));
  // Base window [t_roi.tl + (u0, v0), t_roi.br + (u1, v1)), zero outside the base.
  const cv::Rect window(t_roi.tl() + cv::Point(u0, v0), t_roi.br() + cv::Point(u1, v1));
  cv::Mat base_window(window.size(), CV_32F, cv::mean(p.base));
  const cv::Rect inside = window & cv::Rect(0, 0, p.base.cols, p.base.rows);
  p.base(inside).copyTo(base_window(inside - window.tl()));
  cv::Mat score;
  cv::matchTemplate(base_window, p.templ(t_roi), score, cv::TM_CCOEFF_NORMED);
  cv::Point loc;
  cv::minMaxLoc(score, nullptr, nullptr, nullptr, &loc);
  double dx = 0, dy = 0;
  if (loc.x > 0 && loc.x + 1 < score.cols) {
    dx = ParabolaDelta(score.at<float>(loc.y, loc.x - 1), score.at<float>(loc),
                       score.at<float>(loc.y, loc.x + 1));
  }
  if (loc.y > 0 && loc.y + 1 < score.rows) {
    dy = ParabolaDelta(score.at<float>(loc.y - 1, loc.x), score.at<float>(loc),
                       score.at<float>(loc.y + 1, loc.x));
  }
  return Eigen::Vector2d(u0 + loc.x + dx, v0 + loc.y + dy);
}

// Phase correlation of the whole images (no-data mean-filled, Hann window); of the periodic
// aliases, the one nearest the prediction. The filling and timing are in its time.
Eigen::Vector2d PhaseCorrelation(const Pair& p, const cv::Mat& hann) {
  const cv::Point2d s =
      cv::phaseCorrelate(FillNoData(p.base, p.base_mask), FillNoData(p.templ, p.templ_mask), hann);
  // phaseCorrelate(a, b) returns d with b(x) ~ a(x - d): template p <-> base p - d.
  Eigen::Vector2d best(-s.x, -s.y);
  double best_d = 1e300;
  for (int kx = -1; kx <= 1; ++kx) {
    for (int ky = -1; ky <= 1; ++ky) {
      const Eigen::Vector2d c(-s.x + kx * p.base.cols, -s.y + ky * p.base.rows);
      if ((c - p.predicted).norm() < best_d) {
        best_d = (c - p.predicted).norm();
        best = c;
      }
    }
  }
  return best;
}

// CPU time of this thread: the machine is shared, so wall time is reported beside it.
double ThreadCpuMs() {
  timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

struct Tally {
  int n = 0, good = 0, ok_status = 0, ok_wrong = 0, near_miss = 0;
  double ms = 0.0, cpu_ms = 0.0, sq_err_good = 0.0;
  void Add(bool is_ok, double err, double elapsed_ms, double elapsed_cpu_ms) {
    ++n;
    ms += elapsed_ms;
    cpu_ms += elapsed_cpu_ms;
    ok_status += is_ok;
    if (is_ok && err < 1.0) {
      ++good;
      sq_err_good += err * err;
    }
    if (is_ok && !(err < 1.0)) ++ok_wrong;
    if (is_ok && err >= 1.0 && err < 3.0) ++near_miss;
  }
  double Rate() const { return n ? double(good) / n : 0.0; }
  double Ms() const { return n ? ms / n : 0.0; }
  double CpuMs() const { return n ? cpu_ms / n : 0.0; }
  double Rmse() const { return good ? std::sqrt(sq_err_good / good) : 0.0; }
};

}  // namespace

int main(int argc, char** argv) {
  std::map<std::string, std::string> args = {{"--json", ""},
                                             {"--pairs", "48"},
                                             {"--psnr", "35,30,25,20"},
                                             {"--blur", "1,2,3,4"},
                                             {"--radius", "64"},
                                             {"--sigma", ""},
                                             {"--floor", ""},
                                             {"--flat", ""},
                                             {"--criterion", ""},
                                             {"--subpixel", ""},
                                             {"--methods", "scd,tm,pc"},
                                             {"--seed", "1"},
                                             {"--pyramid", ""},
                                             {"--coarse_sigma", ""},
                                             {"--subpixel_step", ""},
                                             {"--min_ratio", ""},
                                             {"--weight_cap", ""},
                                             {"--template_step", ""}};
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!args.count(argv[i])) {
      std::fprintf(stderr, "unknown option %s\n", argv[i]);
      return 2;
    }
    args[argv[i]] = argv[i + 1];
  }
  cv::setNumThreads(1);
  // Options not given keep the library's defaults.
  ScdOptions options;
  auto set = [&args](const char* name, auto* field) {
    using Field = std::decay_t<decltype(*field)>;
    if (!args[name].empty()) *field = static_cast<Field>(std::stod(args[name]));
  };
  set("--sigma", &options.gradient_sigma_px);
  set("--floor", &options.noise_floor_sigmas);
  set("--pyramid", &options.pyramid_factor);
  set("--coarse_sigma", &options.coarse_gradient_sigma_px);
  set("--subpixel_step", &options.subpixel_step_px);
  set("--min_ratio", &options.min_peak_ratio);
  set("--weight_cap", &options.magnitude_weight_cap);
  set("--template_step", &options.fine_template_step);
  if (args["--flat"] == "mask") options.flat_handling = irmosaic::ScdFlatHandling::kMaskOut;
  if (args["--flat"] == "zero") options.flat_handling = irmosaic::ScdFlatHandling::kZero;
  if (args["--flat"] == "soft") options.flat_handling = irmosaic::ScdFlatHandling::kSoft;
  if (args["--criterion"] == "scd") options.peak_criterion = irmosaic::ScdPeakCriterion::kScd;
  if (args["--criterion"] == "sig") {
    options.peak_criterion = irmosaic::ScdPeakCriterion::kSignificance;
  }
  if (args["--subpixel"] == "gauss") options.subpixel = irmosaic::ScdSubpixel::kGaussian;
  const double radius = std::stod(args["--radius"]);
  const std::string methods = args["--methods"];
  const bool run_tm = methods.find("tm") != std::string::npos;
  const bool run_pc = methods.find("pc") != std::string::npos;
  const unsigned seed = unsigned(std::stoul(args["--seed"]));
  const std::vector<Scene> scenes = MakeScenes(std::stoi(args["--pairs"]), seed);

  ScdMatcher matcher(options);
  cv::Mat hann;
  cv::createHanningWindow(hann, kCrop, CV_32F);
  {  // Warm-up so plan creation is not timed.
    const Pair p = Render(scenes[0], 40.0, 0.0, 1);
    matcher.Match(p.base, p.base_mask, p.templ, p.templ_mask, p.predicted, radius);
  }

  nlohmann::json rows = nlohmann::json::array();
  std::printf("%zu pairs 640x512, 15-25 %% valid overlap, radius %.0f px, 1 thread\n",
              scenes.size(), radius);
  std::printf("%5s %4s | %-29s | %-18s | %-18s\n", "psnr", "blur", "SCD ok/<1px/rmse/cpu ms/wall",
              "TM <1px/cpu/wall", "PC <1px/cpu/wall");
  Tally scd_all;
  for (double psnr : ParseList(args["--psnr"])) {
    for (double blur : ParseList(args["--blur"])) {
      Tally scd, tm, pc;
      std::map<std::string, int> statuses;
      for (size_t i = 0; i < scenes.size(); ++i) {
        const Pair p = Render(scenes[i], psnr, blur, seed * 7919u + unsigned(i));
        cv::TickMeter t;
        double cpu0 = ThreadCpuMs();
        t.start();
        const ScdResult r =
            matcher.Match(p.base, p.base_mask, p.templ, p.templ_mask, p.predicted, radius);
        t.stop();
        double cpu = ThreadCpuMs() - cpu0;
        scd.Add(r.ok(), (r.offset - p.truth).norm(), t.getTimeMilli(), cpu);
        scd_all.Add(r.ok(), (r.offset - p.truth).norm(), t.getTimeMilli(), cpu);
        statuses[irmosaic::ToString(r.status)]++;
        if (run_tm) {
          t.reset();
          cpu0 = ThreadCpuMs();
          t.start();
          const Eigen::Vector2d o = MatchTemplateCcoeff(p, radius);
          t.stop();
          cpu = ThreadCpuMs() - cpu0;
          tm.Add(true, (o - p.truth).norm(), t.getTimeMilli(), cpu);
        }
        if (run_pc) {
          t.reset();
          cpu0 = ThreadCpuMs();
          t.start();
          const Eigen::Vector2d o = PhaseCorrelation(p, hann);
          t.stop();
          cpu = ThreadCpuMs() - cpu0;
          pc.Add(true, (o - p.truth).norm(), t.getTimeMilli(), cpu);
        }
      }
      std::printf(
          "%5.0f %4.0f | %3d/%3d/%5.3f/%5.2f/%6.2f | %4.2f/%5.2f/%6.2f | %4.2f/%5.2f/%6.2f  "
          "(SCD ok-but-wrong %d)\n",
          psnr, blur, scd.ok_status, scd.good, scd.Rmse(), scd.CpuMs(), scd.Ms(), tm.Rate(),
          tm.CpuMs(), tm.Ms(), pc.Rate(), pc.CpuMs(), pc.Ms(), scd.ok_wrong);
      rows.push_back({{"psnr_db", psnr},
                      {"blur_sigma_px", blur},
                      {"pairs", scd.n},
                      {"scd",
                       {{"success_rate", scd.Rate()},
                        {"ok_status", scd.ok_status},
                        {"ok_but_wrong", scd.ok_wrong},
                        {"rmse_px_of_successes", scd.Rmse()},
                        {"ms_per_pair", scd.Ms()},
                        {"cpu_ms_per_pair", scd.CpuMs()},
                        {"statuses", statuses}}},
                      {"match_template_ccoeff_normed",
                       {{"success_rate", tm.Rate()},
                        {"ms_per_pair", tm.Ms()},
                        {"cpu_ms_per_pair", tm.CpuMs()},
                        {"rmse_px_of_successes", tm.Rmse()}}},
                      {"phase_correlate",
                       {{"success_rate", pc.Rate()},
                        {"ms_per_pair", pc.Ms()},
                        {"cpu_ms_per_pair", pc.CpuMs()},
                        {"rmse_px_of_successes", pc.Rmse()}}}});
    }
  }
  std::printf(
      "SCD overall: %d/%d within 1 px (%.3f), %d ok-but-wrong (%d of them within 3 px), %.2f "
      "ms/pair\n",
      scd_all.good, scd_all.n, scd_all.Rate(), scd_all.ok_wrong, scd_all.near_miss, scd_all.Ms());
  std::printf("SCD CPU time: %.2f ms/pair (thread CPU; wall above)\n", scd_all.CpuMs());
  if (!args["--json"].empty()) {
    nlohmann::json doc = {{"benchmark", "scd"},
                          {"options",
                           {{"gradient_sigma_px", options.gradient_sigma_px},
                            {"noise_floor_sigmas", options.noise_floor_sigmas},
                            {"flat_handling", int(options.flat_handling)},
                            {"peak_criterion", int(options.peak_criterion)},
                            {"subpixel", int(options.subpixel)},
                            {"subpixel_step_px", options.subpixel_step_px},
                            {"min_peak_ratio", options.min_peak_ratio},
                            {"pyramid_factor", options.pyramid_factor},
                            {"coarse_gradient_sigma_px", options.coarse_gradient_sigma_px},
                            {"fine_template_step", options.fine_template_step},
                            {"radius_px", radius}}},
                          {"pairs", scenes.size()},
                          {"overall_scd_success_rate", scd_all.Rate()},
                          {"overall_scd_ms_per_pair", scd_all.Ms()},
                          {"overall_scd_cpu_ms_per_pair", scd_all.CpuMs()},
                          {"rows", rows}};
    std::ofstream(args["--json"]) << doc.dump(2) << "\n";
  }
  return 0;
}
