// SCD coarse matching against cv::matchTemplate (TM_CCOEFF_NORMED) and cv::phaseCorrelate:
// success rate (error < 1 px) and ms per 640x512 pair over noise and blur, one core.
//
//   scd_bench [--json FILE] [--pairs N] [--psnr 35,30,25,20] [--blur 1,2,3,4] [--radius 64]
//             [--sigma 2] [--floor 2] [--flat zero|mask] [--criterion sig|scd]
//             [--subpixel parabola|gauss] [--methods scd,tm,pc] [--seed 1]
//
// Pairs: real thermal frames (shared/data/thermal) warped by an oblique homography onto a
// 1150x760 "ortho" canvas (irregular valid area), two 640x512 crops with 15-25 % valid overlap
// cut from it (the template's canvas moved by a random sub-pixel shift), random warped-frame
// footprints as masks, template gain 0.7-1.4 and offset +-20 % of range, pose error uniform in
// +-60 px per axis, search radius 64 px. Per condition: Gaussian blur of the template, then
// white noise on both at the given PSNR (8-bit range). Same pairs and noise for every method.
#include <algorithm>
#include <cmath>
#include <cstdio>
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

struct Pair {
  cv::Mat base, base_mask, templ, templ_mask;  // CV_32F images, CV_8U masks
  Eigen::Vector2d truth, predicted;
  double overlap = 0.0;
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

std::vector<Pair> MakePairs(int count, unsigned seed) {
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
  const cv::Size canvas(1150, 760), size(640, 512);
  const std::vector<cv::Point2f> src = {{0, 0}, {640, 0}, {640, 512}, {0, 512}};
  const std::vector<cv::Point2f> dst = {{0, 0}, {1150, 0}, {950, 760}, {200, 760}};
  const cv::Mat ortho_from_image = cv::getPerspectiveTransform(src, dst);
  std::vector<Pair> pairs;
  for (int i = 0; i < count; ++i) {
    cv::Mat frame = cv::imread(files[i % files.size()], cv::IMREAD_GRAYSCALE);
    frame.convertTo(frame, CV_32F);
    const Eigen::Vector2d sub(uni(rng) - 0.5, uni(rng) - 0.5);
    const cv::Mat shift = (cv::Mat_<double>(3, 3) << 1, 0, sub.x(), 0, 1, sub.y(), 0, 0, 1);
    const cv::Mat all(frame.size(), CV_8U, cv::Scalar(255));
    cv::Mat ob, ot, mb, mt;
    cv::warpPerspective(frame, ob, ortho_from_image, canvas, cv::INTER_LINEAR);
    cv::warpPerspective(all, mb, ortho_from_image, canvas, cv::INTER_NEAREST);
    cv::warpPerspective(frame, ot, shift * ortho_from_image, canvas, cv::INTER_LINEAR);
    cv::warpPerspective(all, mt, shift * ortho_from_image, canvas, cv::INTER_NEAREST);
    Pair p;
    cv::Rect a, b;
    for (int attempt = 0; attempt < 5000; ++attempt) {
      a = cv::Rect(cv::Point(int(uni(rng) * (canvas.width - size.width)),
                             int(uni(rng) * (canvas.height - size.height))),
                   size);
      b = cv::Rect(cv::Point(int(uni(rng) * (canvas.width - size.width)),
                             int(uni(rng) * (canvas.height - size.height))),
                   size);
      p.base_mask = mb(a) & RandomFootprint(size, &rng);
      p.templ_mask = mt(b) & RandomFootprint(size, &rng);
      p.overlap = ValidOverlap(p.base_mask, p.templ_mask, b.tl() - a.tl());
      if (p.overlap >= 0.15 && p.overlap <= 0.25) break;
    }
    p.base = ob(a).clone();
    const double gain = 0.7 + 0.7 * uni(rng), offset = (uni(rng) - 0.5) * 0.4 * 255.0;
    p.templ = ot(b) * gain + offset;
    p.truth = Eigen::Vector2d(b.x - a.x, b.y - a.y) - sub;
    p.predicted = p.truth + Eigen::Vector2d(120.0 * (uni(rng) - 0.5), 120.0 * (uni(rng) - 0.5));
    pairs.push_back(std::move(p));
  }
  return pairs;
}

// Degraded copy: template blurred by blur_sigma, white noise at psnr_db on both; no-data = 0.
Pair Degrade(const Pair& in, double psnr_db, double blur_sigma, unsigned seed) {
  Pair p = in;
  cv::RNG rng(seed);
  const double noise_std = 255.0 / std::pow(10.0, psnr_db / 20.0);
  if (blur_sigma > 0) cv::GaussianBlur(in.templ, p.templ, cv::Size(), blur_sigma);
  cv::Mat noise(p.base.size(), CV_32F);
  rng.fill(noise, cv::RNG::NORMAL, 0.0, noise_std);
  p.base = in.base + noise;
  rng.fill(noise, cv::RNG::NORMAL, 0.0, noise_std);
  p.templ = p.templ + noise;
  p.base.setTo(0.0f, ~p.base_mask);
  p.templ.setTo(0.0f, ~p.templ_mask);
  return p;
}

double ParabolaDelta(double l, double c, double r) {
  const double curv = l - 2 * c + r;
  return curv < 0 ? std::clamp(0.5 * (l - r) / curv, -0.5, 0.5) : 0.0;
}

// TM_CCOEFF_NORMED of the template part that can overlap, over the same search window.
Eigen::Vector2d MatchTemplateCcoeff(const Pair& p, double radius) {
  const int u0 = int(std::ceil(p.predicted.x() - radius)),
            u1 = int(std::floor(p.predicted.x() + radius));
  const int v0 = int(std::ceil(p.predicted.y() - radius)),
            v1 = int(std::floor(p.predicted.y() + radius));
  const cv::Rect t_roi(cv::Point(std::max(0, -u1), std::max(0, -v1)),
                       cv::Point(std::min(p.templ.cols, p.base.cols - u0),
                                 std::min(p.templ.rows, p.base.rows - v0)));
  // Base window [t_roi.tl + (u0, v0), t_roi.br + (u1, v1)), zero outside the base.
  const cv::Rect window(t_roi.tl() + cv::Point(u0, v0), t_roi.br() + cv::Point(u1, v1));
  cv::Mat base_window = cv::Mat::zeros(window.size(), CV_32F);
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

// Phase correlation of the whole images (Hann window); of the periodic aliases, the one
// nearest the prediction.
Eigen::Vector2d PhaseCorrelation(const Pair& p, const cv::Mat& hann) {
  const cv::Point2d s = cv::phaseCorrelate(p.base, p.templ, hann);
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

struct Tally {
  int n = 0, good = 0, ok_status = 0, ok_wrong = 0;
  double ms = 0.0, sq_err_good = 0.0;
  void Add(bool is_ok, double err, double elapsed_ms) {
    ++n;
    ms += elapsed_ms;
    ok_status += is_ok;
    if (is_ok && err < 1.0) {
      ++good;
      sq_err_good += err * err;
    }
    if (is_ok && !(err < 1.0)) ++ok_wrong;
  }
  double Rate() const { return n ? double(good) / n : 0.0; }
  double Ms() const { return n ? ms / n : 0.0; }
  double Rmse() const { return good ? std::sqrt(sq_err_good / good) : 0.0; }
};

}  // namespace

int main(int argc, char** argv) {
  std::map<std::string, std::string> args = {{"--json", ""},
                                             {"--pairs", "48"},
                                             {"--psnr", "35,30,25,20"},
                                             {"--blur", "1,2,3,4"},
                                             {"--radius", "64"},
                                             {"--sigma", "2"},
                                             {"--floor", "2"},
                                             {"--flat", "zero"},
                                             {"--criterion", "sig"},
                                             {"--subpixel", "parabola"},
                                             {"--methods", "scd,tm,pc"},
                                             {"--seed", "1"},
                                             {"--pyramid", "4"},
                                             {"--coarse_sigma", "1"}};
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!args.count(argv[i])) {
      std::fprintf(stderr, "unknown option %s\n", argv[i]);
      return 2;
    }
    args[argv[i]] = argv[i + 1];
  }
  cv::setNumThreads(1);
  ScdOptions options;
  options.gradient_sigma_px = std::stod(args["--sigma"]);
  options.noise_floor_sigmas = std::stod(args["--floor"]);
  options.flat_handling = args["--flat"] == "mask" ? irmosaic::ScdFlatHandling::kMaskOut
                                                   : irmosaic::ScdFlatHandling::kZero;
  options.peak_criterion = args["--criterion"] == "scd" ? irmosaic::ScdPeakCriterion::kScd
                                                        : irmosaic::ScdPeakCriterion::kSignificance;
  options.subpixel = args["--subpixel"] == "gauss" ? irmosaic::ScdSubpixel::kGaussian
                                                   : irmosaic::ScdSubpixel::kParabola;
  options.pyramid_factor = std::stoi(args["--pyramid"]);
  options.coarse_gradient_sigma_px = std::stod(args["--coarse_sigma"]);
  const double radius = std::stod(args["--radius"]);
  const std::string methods = args["--methods"];
  const bool run_tm = methods.find("tm") != std::string::npos;
  const bool run_pc = methods.find("pc") != std::string::npos;
  const unsigned seed = unsigned(std::stoul(args["--seed"]));
  const std::vector<Pair> pairs = MakePairs(std::stoi(args["--pairs"]), seed);

  ScdMatcher matcher(options);
  cv::Mat hann;
  cv::createHanningWindow(hann, pairs.front().base.size(), CV_32F);
  // Warm-up so plan creation is not timed.
  matcher.Match(pairs[0].base, pairs[0].base_mask, pairs[0].templ, pairs[0].templ_mask,
                pairs[0].predicted, radius);

  nlohmann::json rows = nlohmann::json::array();
  std::printf("%zu pairs 640x512, 15-25 %% valid overlap, radius %.0f px, 1 thread\n", pairs.size(),
              radius);
  std::printf("%5s %4s | %-22s | %-14s | %-14s\n", "psnr", "blur", "SCD ok/<1px/rmse/ms",
              "TM <1px/ms", "PC <1px/ms");
  Tally scd_all;
  for (double psnr : ParseList(args["--psnr"])) {
    for (double blur : ParseList(args["--blur"])) {
      Tally scd, tm, pc;
      std::map<std::string, int> statuses;
      for (size_t i = 0; i < pairs.size(); ++i) {
        const Pair p = Degrade(pairs[i], psnr, blur, seed * 7919u + unsigned(i));
        cv::TickMeter t;
        t.start();
        const ScdResult r =
            matcher.Match(p.base, p.base_mask, p.templ, p.templ_mask, p.predicted, radius);
        t.stop();
        scd.Add(r.ok(), (r.offset - p.truth).norm(), t.getTimeMilli());
        scd_all.Add(r.ok(), (r.offset - p.truth).norm(), t.getTimeMilli());
        statuses[irmosaic::ToString(r.status)]++;
        if (run_tm) {
          t.reset();
          t.start();
          const Eigen::Vector2d o = MatchTemplateCcoeff(p, radius);
          t.stop();
          tm.Add(true, (o - p.truth).norm(), t.getTimeMilli());
        }
        if (run_pc) {
          t.reset();
          t.start();
          const Eigen::Vector2d o = PhaseCorrelation(p, hann);
          t.stop();
          pc.Add(true, (o - p.truth).norm(), t.getTimeMilli());
        }
      }
      std::printf(
          "%5.0f %4.0f | %3d/%3d/%5.3f/%6.2f | %5.2f/%7.2f | %5.2f/%7.2f  (ok-but-wrong %d)\n",
          psnr, blur, scd.ok_status, scd.good, scd.Rmse(), scd.Ms(), tm.Rate(), tm.Ms(), pc.Rate(),
          pc.Ms(), scd.ok_wrong);
      rows.push_back({{"psnr_db", psnr},
                      {"blur_sigma_px", blur},
                      {"pairs", scd.n},
                      {"scd",
                       {{"success_rate", scd.Rate()},
                        {"ok_status", scd.ok_status},
                        {"ok_but_wrong", scd.ok_wrong},
                        {"rmse_px_of_successes", scd.Rmse()},
                        {"ms_per_pair", scd.Ms()},
                        {"statuses", statuses}}},
                      {"match_template_ccoeff_normed",
                       {{"success_rate", tm.Rate()},
                        {"ms_per_pair", tm.Ms()},
                        {"rmse_px_of_successes", tm.Rmse()}}},
                      {"phase_correlate",
                       {{"success_rate", pc.Rate()},
                        {"ms_per_pair", pc.Ms()},
                        {"rmse_px_of_successes", pc.Rmse()}}}});
    }
  }
  std::printf("SCD overall: %d/%d within 1 px (%.3f), %d ok-but-wrong, %.2f ms/pair\n",
              scd_all.good, scd_all.n, scd_all.Rate(), scd_all.ok_wrong, scd_all.Ms());
  if (!args["--json"].empty()) {
    nlohmann::json doc = {{"benchmark", "scd"},
                          {"options",
                           {{"gradient_sigma_px", options.gradient_sigma_px},
                            {"noise_floor_sigmas", options.noise_floor_sigmas},
                            {"flat", args["--flat"]},
                            {"criterion", args["--criterion"]},
                            {"subpixel", args["--subpixel"]},
                            {"pyramid_factor", options.pyramid_factor},
                            {"coarse_gradient_sigma_px", options.coarse_gradient_sigma_px},
                            {"radius_px", radius}}},
                          {"pairs", pairs.size()},
                          {"overall_scd_success_rate", scd_all.Rate()},
                          {"overall_scd_ms_per_pair", scd_all.Ms()},
                          {"rows", rows}};
    std::ofstream(args["--json"]) << doc.dump(2) << "\n";
  }
  return 0;
}
