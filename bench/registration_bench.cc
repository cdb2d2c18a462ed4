// Fine registration benchmark (issue 5).
//  Table 1: single-patch FLSM vs TLSM: convergence, RMSE against truth, time per patch.
//  Tables 3-4: our pipeline (key points + FLSM + RANSAC [+ joint FLSM]) vs OpenCV ORB, SIFT,
//  AKAZE (+RANSAC) and ECC (MOTION_HOMOGRAPHY), all given the same coarse translation:
//  success (corner RMSE over the overlap < 1 px), median corner RMSE, ms per pair, at 4 noise
//  and 4 blur levels on simulated pairs from real images, and on real thermal pairs with noise
//  (reference: our clean-pair result). One run, one core.
// Usage: registration_bench [--pairs N] [--json FILE]
#include <Eigen/Dense>
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/video/tracking.hpp>
#include <random>

#include "../tests/registration_pairs.h"
#include "irmosaic/registration.h"
#include "test_data.h"

namespace {

using irmosaic::testing::MakePair;
using irmosaic::testing::PairDegradation;
// Thread CPU time: the machine is shared, and the load inflates wall time far more.
struct Clock {
  using time_point = double;  // ms
  static time_point now() {
    timespec t;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
    return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
  }
};

double Ms(Clock::time_point a, Clock::time_point b) { return b - a; }

struct Case {
  cv::Mat base, templ;
  Eigen::Matrix3d truth = Eigen::Matrix3d::Identity();  // Or the clean reference (thermal).
  Eigen::Vector2d prior = Eigen::Vector2d::Zero();
  cv::Rect2d overlap;
};

// A method: returns false on failure, else base_from_template.
using Method = std::function<bool(const Case&, Eigen::Matrix3d*)>;

Eigen::Matrix3d ToEigen(const cv::Mat& m) {
  Eigen::Matrix3d e;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) e(r, c) = m.at<double>(r, c);
  }
  return e;
}

Method FeatureMethod(cv::Ptr<cv::Feature2D> detector, int norm) {
  return [detector, norm](const Case& c, Eigen::Matrix3d* h) {
    std::vector<cv::KeyPoint> kb, kt;
    cv::Mat db, dt;
    detector->detectAndCompute(c.base, cv::noArray(), kb, db);
    detector->detectAndCompute(c.templ, cv::noArray(), kt, dt);
    if (kb.size() < 4 || kt.size() < 4) return false;
    cv::BFMatcher matcher(norm);
    std::vector<std::vector<cv::DMatch>> knn;
    matcher.knnMatch(dt, db, knn, 2);
    std::vector<cv::Point2f> from, to;
    for (const auto& m : knn) {
      if (m.size() < 2 || m[0].distance > 0.8f * m[1].distance) continue;
      const cv::Point2f p = kt[m[0].queryIdx].pt, q = kb[m[0].trainIdx].pt;
      // The same prior as ours: matches must agree with the coarse translation (20 px).
      if (std::hypot(q.x - p.x - c.prior.x(), q.y - p.y - c.prior.y()) > 20.0) continue;
      from.push_back(p);
      to.push_back(q);
    }
    if (from.size() < 8) return false;
    const cv::Mat m = cv::findHomography(from, to, cv::RANSAC, 3.0);
    if (m.empty()) return false;
    *h = ToEigen(m);
    return true;
  };
}

bool Ecc(const Case& c, Eigen::Matrix3d* h) {
  // ECC on the predicted overlap of the template only (the rest has no counterpart).
  const cv::Rect box = cv::Rect(c.overlap) & cv::Rect(0, 0, c.templ.cols, c.templ.rows);
  if (box.width < 16 || box.height < 16) return false;
  cv::Mat warp = cv::Mat::eye(3, 3, CV_32F);
  warp.at<float>(0, 2) = static_cast<float>(c.prior.x() + box.x);
  warp.at<float>(1, 2) = static_cast<float>(c.prior.y() + box.y);
  try {
    cv::findTransformECC(
        c.templ(box), c.base, warp, cv::MOTION_HOMOGRAPHY,
        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 50, 1e-4), cv::noArray(),
        5);
  } catch (const cv::Exception&) {
    return false;
  }
  cv::Mat w64;
  warp.convertTo(w64, CV_64F);
  Eigen::Matrix3d shift = Eigen::Matrix3d::Identity();
  shift(0, 2) = -box.x;
  shift(1, 2) = -box.y;
  *h = ToEigen(w64) * shift;
  return true;
}

struct Row {
  std::string set, condition, method;
  int pairs = 0, success = 0;
  double median_rmse = 0, ms = 0;
};

Row Evaluate(const std::string& set, const std::string& condition, const std::string& name,
             const Method& method, const std::vector<Case>& cases) {
  Row row{set, condition, name};
  std::vector<double> errors;
  double total_ms = 0;
  for (const Case& c : cases) {
    Eigen::Matrix3d h;
    const auto t0 = Clock::now();
    const bool ok = method(c, &h);
    total_ms += Ms(t0, Clock::now());
    const double e = ok && h.allFinite() ? irmosaic::CornerRmse(h, c.truth, c.overlap) : 1e9;
    ++row.pairs;
    if (e < 1.0) {
      ++row.success;
      errors.push_back(e);
    }
  }
  std::sort(errors.begin(), errors.end());
  row.median_rmse = errors.empty() ? NAN : errors[errors.size() / 2];
  row.ms = total_ms / std::max(1, row.pairs);
  return row;
}

cv::Rect2d OverlapInTemplate(const Eigen::Matrix3d& base_from_template, cv::Size size) {
  const Eigen::Matrix3d inv = base_from_template.inverse();
  double x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(0, 0), Eigen::Vector2d(size.width - 1, 0),
        Eigen::Vector2d(size.width - 1, size.height - 1), Eigen::Vector2d(0, size.height - 1)}) {
    const Eigen::Vector2d q = (inv * c.homogeneous()).hnormalized();
    x0 = std::min(x0, q.x()), y0 = std::min(y0, q.y());
    x1 = std::max(x1, q.x()), y1 = std::max(y1, q.y());
  }
  x0 = std::max(x0, 0.0), y0 = std::max(y0, 0.0);
  x1 = std::min(x1, size.width - 1.0), y1 = std::min(y1, size.height - 1.0);
  return {x0, y0, x1 - x0, y1 - y0};
}

}  // namespace

int main(int argc, char** argv) {
  int pairs_per_source = 6;
  std::string json_path;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--pairs") && i + 1 < argc) pairs_per_source = std::atoi(argv[++i]);
    if (!std::strcmp(argv[i], "--json") && i + 1 < argc) json_path = argv[++i];
  }
  cv::setNumThreads(1);
  using irmosaic::testing::SharedDataPath;
  const std::vector<std::string> sources = {"geotiff/UTM2GTIF.tiff",
                                            "geotiff/naip/m_4709963_se_14_1_20090818.tif",
                                            "geotiff/naip/m_4709963_se_14_1_20190904.tif"};
  std::vector<cv::Mat> images;
  for (const auto& s : sources)
    images.push_back(cv::imread(SharedDataPath(s), cv::IMREAD_GRAYSCALE));

  nlohmann::json out;
  // ---- Table 1: single patches, FLSM vs TLSM.
  std::printf(
      "Table 1: single-patch LSM (key points of simulated pairs, 1 deg distortion, gain 0.8,"
      " blur 2, start = prior)\n%-8s %-6s %8s %10s %10s %10s\n",
      "PSNR", "method", "patches", "converged", "rmse_px", "us/patch");
  for (double psnr : {0.0, 35.0, 30.0, 25.0, 20.0}) {
    for (auto method : {irmosaic::LsmMethod::kFast, irmosaic::LsmMethod::kTraditional}) {
      irmosaic::LsmOptions lo;
      lo.method = method;
      irmosaic::LsmMatcher lsm(lo);
      std::mt19937 rng(100);
      int patches = 0, converged = 0;
      double sq = 0, us = 0;
      for (const cv::Mat& source : images) {
        for (int i = 0; i < pairs_per_source; ++i) {
          PairDegradation d;
          d.gain = 0.8, d.offset = 20, d.blur_sigma_px = 2, d.psnr_db = psnr;
          const auto pair = MakePair(source, d, i % 2 == 0, &rng);
          cv::Mat base_f, templ_f, valid(pair.templ.size(), CV_8U, cv::Scalar(0));
          pair.base.convertTo(base_f, CV_32F);
          pair.templ.convertTo(templ_f, CV_32F);
          const int half = 28;
          const cv::Rect inner = cv::Rect(pair.overlap_in_template) &
                                 cv::Rect(half, half, 640 - 2 * half, 512 - 2 * half);
          if (inner.empty()) continue;
          valid(inner).setTo(255);
          for (const Eigen::Vector2d& p : irmosaic::DetectKeypoints(templ_f, valid)) {
            const Eigen::Vector2d truth = (pair.base_from_template * p.homogeneous()).hnormalized();
            const auto t0 = Clock::now();
            const auto r = lsm.Match(base_f, templ_f, p, p + pair.prior_offset);
            us += 1000.0 * Ms(t0, Clock::now());
            ++patches;
            if (!r.ok()) continue;
            ++converged;
            sq += (r.position_in_base - truth).squaredNorm();
          }
        }
      }
      const char* name = method == irmosaic::LsmMethod::kFast ? "FLSM" : "TLSM";
      const double rmse = std::sqrt(sq / std::max(1, converged));
      std::printf("%-8.0f %-6s %8d %10d %10.3f %10.1f\n", psnr, name, patches, converged, rmse,
                  us / std::max(1, patches));
      out["table1"].push_back({{"psnr_db", psnr},
                               {"method", name},
                               {"patches", patches},
                               {"converged", converged},
                               {"rmse_px", rmse},
                               {"us_per_patch", us / std::max(1, patches)}});
    }
  }

  // ---- Tables 3-4: pipelines.
  irmosaic::FineRegistrar ours_registrar;
  irmosaic::FineRegistrationOptions tlsm_options;
  tlsm_options.lsm.method = irmosaic::LsmMethod::kTraditional;
  irmosaic::FineRegistrar tlsm_registrar(tlsm_options);
  std::vector<std::pair<std::string, Method>> methods = {
      {"ours (FLSM)",
       [&](const Case& c, Eigen::Matrix3d* h) {
         const auto r = ours_registrar.Register(c.base, {}, c.templ, {}, c.prior);
         *h = r.base_from_template;
         return r.ok();
       }},
      {"ours (TLSM)",
       [&](const Case& c, Eigen::Matrix3d* h) {
         const auto r = tlsm_registrar.Register(c.base, {}, c.templ, {}, c.prior);
         *h = r.base_from_template;
         return r.ok();
       }},
      {"ORB", FeatureMethod(cv::ORB::create(2000), cv::NORM_HAMMING)},
      {"SIFT", FeatureMethod(cv::SIFT::create(), cv::NORM_L2)},
      {"AKAZE", FeatureMethod(cv::AKAZE::create(), cv::NORM_HAMMING)},
      {"ECC", Ecc},
  };
  std::vector<Row> rows;
  std::printf(
      "\nTables 3-4: pairs registered given the prior translation (success: corner RMSE over"
      " the overlap < 1 px)\n%-9s %-14s %-12s %6s %8s %11s %8s\n",
      "set", "condition", "method", "pairs", "success", "median_px", "ms/pair");
  auto report = [&](const Row& r) {
    std::printf("%-9s %-14s %-12s %6d %8d %11.3f %8.1f\n", r.set.c_str(), r.condition.c_str(),
                r.method.c_str(), r.pairs, r.success, r.median_rmse, r.ms);
    std::fflush(stdout);
    out["tables34"].push_back({{"set", r.set},
                               {"condition", r.condition},
                               {"method", r.method},
                               {"pairs", r.pairs},
                               {"success_within_1px", r.success},
                               {"median_corner_rmse_px", r.median_rmse},
                               {"ms_per_pair", r.ms}});
  };
  std::vector<std::pair<std::string, PairDegradation>> conditions;
  for (double psnr : {35.0, 30.0, 25.0, 20.0}) {
    PairDegradation d;
    d.gain = 0.8, d.offset = 20, d.psnr_db = psnr;
    conditions.push_back({"psnr " + std::to_string(static_cast<int>(psnr)) + " dB", d});
  }
  for (double blur : {1.0, 2.0, 3.0, 4.0}) {
    PairDegradation d;
    d.gain = 0.8, d.offset = 20, d.blur_sigma_px = blur;
    conditions.push_back({"blur " + std::to_string(static_cast<int>(blur)) + " px", d});
  }
  for (const auto& [label, d] : conditions) {
    std::mt19937 rng(200);
    std::vector<Case> cases;
    for (const cv::Mat& source : images) {
      for (int i = 0; i < pairs_per_source; ++i) {
        const auto pair = MakePair(source, d, i % 2 == 0, &rng);
        cases.push_back({pair.base, pair.templ, pair.base_from_template, pair.prior_offset,
                         pair.overlap_in_template});
      }
    }
    for (const auto& [name, method] : methods)
      report(Evaluate("simulated", label, name, method, cases));
  }

  // Real thermal pairs (i, i+1) in continuous stretches; reference: our clean result.
  std::vector<Case> clean;
  for (int first : {0, 5, 8, 15, 18, 20, 26, 29, 31, 37, 40, 42}) {
    char a[64], b[64];
    std::snprintf(a, sizeof(a), "thermal/seq_1_60_30/1_60_30_0_%05d.jpg", first);
    std::snprintf(b, sizeof(b), "thermal/seq_1_60_30/1_60_30_0_%05d.jpg", first + 1);
    Case c;
    c.base = cv::imread(SharedDataPath(a), cv::IMREAD_GRAYSCALE);
    c.templ = cv::imread(SharedDataPath(b), cv::IMREAD_GRAYSCALE);
    cv::Mat fa, fb, window;
    c.base.convertTo(fa, CV_64F);
    c.templ.convertTo(fb, CV_64F);
    cv::createHanningWindow(window, c.base.size(), CV_64F);
    const cv::Point2d shift = cv::phaseCorrelate(fb, fa, window);
    c.prior = {shift.x, shift.y};
    const auto r = ours_registrar.Register(c.base, {}, c.templ, {}, c.prior);
    if (!r.ok()) continue;
    c.truth = r.base_from_template;
    c.overlap = OverlapInTemplate(c.truth, c.templ.size());
    clean.push_back(c);
  }
  for (double psnr : {35.0, 30.0, 25.0, 20.0}) {
    std::mt19937 rng(300);
    std::vector<Case> cases = clean;
    const double sigma = irmosaic::testing::NoiseSigmaForPsnr(psnr);
    for (Case& c : cases) {
      cv::Mat fa, fb;
      c.base.convertTo(fa, CV_32F);
      c.templ.convertTo(fb, CV_32F);
      irmosaic::testing::Degrade(&fa, 1, 0, 0, sigma, &rng, &c.base);
      irmosaic::testing::Degrade(&fb, 1, 0, 0, sigma, &rng, &c.templ);
    }
    const std::string label = "psnr " + std::to_string(static_cast<int>(psnr)) + " dB";
    for (const auto& [name, method] : methods)
      report(Evaluate("thermal", label, name, method, cases));
  }
  if (!json_path.empty()) {
    std::ofstream f(json_path);
    f << out.dump(1) << "\n";
  }
  return 0;
}
