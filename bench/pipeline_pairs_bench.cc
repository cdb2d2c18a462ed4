// Pair registration on the pipeline's own pairs (issues 5 and 10): the Mosaicker runs over the
// first frames of the bundled sample flight (simulated on the fly) and hands each pair it
// registers to MosaickerOptions::on_pair_registered, which keeps the pair's POS orthoimages,
// the predicted offset and the search radius. Every pair is then registered again, one core,
// by each method, and scored against the simulator's truth.
//
//   pipeline_pairs_bench [--frames N] [--first N] [--pairs N] [--repeats N] [--peer-repeats N]
//                        [--no-peers] [--only METHOD] [--json FILE]
//
// Methods: "pipeline" (PipelineRegistrationOptions(), what the Mosaicker runs), "lsm-level-0"
// (the same with the FLSM at full resolution, FineRegistrationOptions::lsm_level), "defaults" (the
// single-pair defaults of `irmosaic register`), and with peers OpenCV ORB and SIFT (+ RANSAC),
// given the same POS prediction (matches must agree with it within the search radius) and the
// orthoimages' masks. Time: thread CPU per pair, the minimum of --repeats registrations (the
// VM's timing noise is +-5-10 % run to run; the minimum is steadier). Accuracy: the truth
// homography between the two orthoimages is O_b * M_b^-1 * M_t * O_t^-1 (O: the orthoimage's
// ortho_from_image, M: the simulator's true mosaic_from_image); the error of a result is the
// RMS over the 4 corners of the true overlap's box (template pixels whose true image falls on
// the base's data) of |H * c - H_true * c|, base pixels; the JSON keeps each accepted pair's
// signed errors at those corners too (`corner_errors`: [x, y, error x, error y] per corner), to
// look for biases the RMS hides. The same RMS over the corners of the template's whole valid
// box (`frame_error_px`) is the error where the placement through this pair extrapolates to:
// the far field of an oblique frame lies well outside the overlap. --first N starts at frame N
// of the flight (the simulator renders any frame on its own). The replayed pipeline results are
// also compared with what the Mosaicker got (they must agree: the capture is faithful).
#include <unistd.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <string>
#include <vector>

#include "irmosaic/mosaicker.h"
#include "irmosaic/registration.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

namespace {

double ThreadCpuMs() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) * 1e3 + static_cast<double>(t.tv_nsec) * 1e-6;
}

Eigen::Vector2d Apply(const Eigen::Matrix3d& h, const Eigen::Vector2d& p) {
  const Eigen::Vector3d q = h * p.homogeneous();
  return q.hnormalized();
}

struct Pair {
  int64_t base = -1, templ = -1;
  Eigen::Vector2d predicted = Eigen::Vector2d::Zero();
  double radius = 0.0;
  bool pipeline_ok = false;  // What the Mosaicker got.
  Eigen::Matrix3d pipeline_h = Eigen::Matrix3d::Identity();
  Eigen::Matrix3d truth = Eigen::Matrix3d::Identity();  // Base ortho px from template ortho px.
  std::array<Eigen::Vector2d, 4> corners;               // True overlap box, template px.
  bool has_overlap = false;
  // The box of the template's whole valid area (template px): where the pair's homography is
  // extrapolated to when the template frame is placed through this pair.
  std::array<Eigen::Vector2d, 4> frame_corners;
};

std::array<Eigen::Vector2d, 4> ValidBox(const cv::Mat& mask) {
  const cv::Rect r = cv::boundingRect(mask);
  const double x0 = r.x, y0 = r.y, x1 = r.br().x - 1, y1 = r.br().y - 1;
  return {Eigen::Vector2d(x0, y0), Eigen::Vector2d(x1, y0), Eigen::Vector2d(x1, y1),
          Eigen::Vector2d(x0, y1)};
}

// The 4 corners of the box of template pixels whose true position falls on the base's data.
bool TrueOverlapBox(const irmosaic::OrthoImage& base, const irmosaic::OrthoImage& templ,
                    const Eigen::Matrix3d& truth, std::array<Eigen::Vector2d, 4>* corners) {
  double x0 = 1e30, y0 = 1e30, x1 = -1e30, y1 = -1e30;
  constexpr int kStep = 2;
  for (int y = 0; y < templ.mask.rows; y += kStep) {
    const uint8_t* row = templ.mask.ptr<uint8_t>(y);
    for (int x = 0; x < templ.mask.cols; x += kStep) {
      if (row[x] == 0) continue;
      const Eigen::Vector2d q = Apply(truth, Eigen::Vector2d(x, y));
      const int bx = static_cast<int>(std::lround(q.x())),
                by = static_cast<int>(std::lround(q.y()));
      if (bx < 0 || by < 0 || bx >= base.mask.cols || by >= base.mask.rows ||
          base.mask.at<uint8_t>(by, bx) == 0) {
        continue;
      }
      x0 = std::min<double>(x0, x);
      y0 = std::min<double>(y0, y);
      x1 = std::max<double>(x1, x);
      y1 = std::max<double>(y1, y);
    }
  }
  if (x1 < x0) return false;
  *corners = {Eigen::Vector2d(x0, y0), Eigen::Vector2d(x1, y0), Eigen::Vector2d(x1, y1),
              Eigen::Vector2d(x0, y1)};
  return true;
}

double CornerRms(const Eigen::Matrix3d& h, const Eigen::Matrix3d& reference,
                 const std::array<Eigen::Vector2d, 4>& corners) {
  double sum = 0.0;
  for (const Eigen::Vector2d& c : corners) {
    sum += (Apply(h, c) - Apply(reference, c)).squaredNorm();
  }
  return std::sqrt(sum / 4.0);
}

double Percentile(std::vector<double> v, double p) {
  if (v.empty()) return std::nan("");
  std::sort(v.begin(), v.end());
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(p * (v.size() - 1) + 0.5));
  return v[k];
}

using Method = std::function<bool(const irmosaic::OrthoImage& base,
                                  const irmosaic::OrthoImage& templ, const Pair& pair,
                                  Eigen::Matrix3d* base_from_template, nlohmann::json* details)>;

Method OursMethod(irmosaic::PairRegistrationOptions options) {
  auto registrar = std::make_shared<irmosaic::PairRegistrar>(options);
  return [registrar](const irmosaic::OrthoImage& base, const irmosaic::OrthoImage& templ,
                     const Pair& pair, Eigen::Matrix3d* h, nlohmann::json* details) {
    const irmosaic::PairRegistration r = registrar->Register(
        base.image, base.mask, templ.image, templ.mask, pair.predicted, pair.radius);
    *h = r.base_from_template;
    *details = {{"status", irmosaic::ToString(r.status)},
                {"keypoints", r.keypoints},
                {"tie_points", r.tie_points.size()},
                {"inliers", r.inliers},
                {"residual_rms_px", r.residual_rms_px},
                {"joint_patches", r.joint_patches},
                {"joint_sigma_px", r.joint_sigma_px},
                {"joint_inlier_patches", r.joint_inlier_patches},
                {"joint_residual_ratio", r.joint_residual_ratio},
                {"offset_from_prediction_px", (r.offset - pair.predicted).norm()},
                {"search_radius_px", pair.radius}};
    if (pair.has_overlap) {
      // Where the truth puts the overlap box's centre, against the prediction: a true offset
      // outside the search radius cannot be found.
      const Eigen::Vector2d c = 0.5 * (pair.corners[0] + pair.corners[2]);
      (*details)["true_offset_from_prediction_px"] =
          (Apply(pair.truth, c) - c - pair.predicted).norm();
    }
    // The single-patch tie points against the truth (base pixels).
    std::vector<double> tie_errors;
    for (const irmosaic::TiePoint& t : r.tie_points) {
      tie_errors.push_back((t.in_base - Apply(pair.truth, t.in_template)).norm());
    }
    (*details)["tie_median_error_px"] =
        tie_errors.empty() ? nlohmann::json(nullptr) : nlohmann::json(Percentile(tie_errors, 0.5));
    return r.ok();
  };
}

// 8-bit copy for OpenCV's detectors: the overlap's 1st-99th percentile range stretched.
cv::Mat To8Bit(const cv::Mat& image, const cv::Mat& mask) {
  if (image.depth() == CV_8U) return image;
  std::vector<float> values;
  for (int y = 0; y < image.rows; y += 4) {
    for (int x = 0; x < image.cols; x += 4) {
      if (mask.at<uint8_t>(y, x) == 0) continue;
      values.push_back(image.depth() == CV_16U ? image.at<uint16_t>(y, x) : image.at<float>(y, x));
    }
  }
  if (values.size() < 2) return cv::Mat::zeros(image.size(), CV_8U);
  std::sort(values.begin(), values.end());
  const double lo = values[values.size() / 100], hi = values[values.size() * 99 / 100];
  cv::Mat out;
  image.convertTo(out, CV_8U, 255.0 / std::max(1.0, hi - lo), -lo * 255.0 / std::max(1.0, hi - lo));
  return out;
}

Method FeatureMethod(cv::Ptr<cv::Feature2D> detector, int norm) {
  return [detector, norm](const irmosaic::OrthoImage& base, const irmosaic::OrthoImage& templ,
                          const Pair& pair, Eigen::Matrix3d* h, nlohmann::json* /*details*/) {
    std::vector<cv::KeyPoint> kb, kt;
    cv::Mat db, dt;
    detector->detectAndCompute(To8Bit(base.image, base.mask), base.mask, kb, db);
    detector->detectAndCompute(To8Bit(templ.image, templ.mask), templ.mask, kt, dt);
    if (kb.size() < 4 || kt.size() < 4) return false;
    cv::BFMatcher matcher(norm);
    std::vector<std::vector<cv::DMatch>> knn;
    matcher.knnMatch(dt, db, knn, 2);
    std::vector<cv::Point2f> from, to;
    for (const auto& m : knn) {
      if (m.size() < 2 || m[0].distance > 0.8f * m[1].distance) continue;
      const cv::Point2f p = kt[m[0].queryIdx].pt, q = kb[m[0].trainIdx].pt;
      // The pipeline's prior: the POS prediction, within the search radius.
      if (std::hypot(q.x - p.x - pair.predicted.x(), q.y - p.y - pair.predicted.y()) >
          pair.radius) {
        continue;
      }
      from.push_back(p);
      to.push_back(q);
    }
    if (from.size() < 8) return false;
    cv::Mat inliers;
    const cv::Mat hm = cv::findHomography(from, to, cv::RANSAC, 2.0, inliers, 2000, 0.995);
    if (hm.empty() || cv::countNonZero(inliers) < 8) return false;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) (*h)(r, c) = hm.at<double>(r, c);
    }
    return true;
  };
}

int Usage(const char* message) {
  std::cerr << "pipeline_pairs_bench: " << message
            << "\nusage: pipeline_pairs_bench [--frames N] [--first N] [--pairs N] [--repeats N] "
               "[--peer-repeats N] [--no-peers] [--only METHOD] [--json FILE]\n";
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  int frames = 110, first = 0, max_pairs = 200, repeats = 5, peer_repeats = 1;
  bool peers = true;
  std::string only;  // One method by name (e.g. for a profile); empty: all.
  std::string json_path = "pipeline_pairs_bench.json";
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto number = [&](int* out) {
      if (i + 1 >= argc) return false;
      char* end = nullptr;
      const long v = std::strtol(argv[++i], &end, 10);
      if (*end != '\0' || v < 1 || v > 1000000) return false;
      *out = static_cast<int>(v);
      return true;
    };
    if (a == "--frames") {
      if (!number(&frames)) return Usage("--frames needs a whole number >= 1");
    } else if (a == "--first") {
      if (!number(&first)) return Usage("--first needs a whole number >= 1");
    } else if (a == "--pairs") {
      if (!number(&max_pairs)) return Usage("--pairs needs a whole number >= 1");
    } else if (a == "--repeats") {
      if (!number(&repeats)) return Usage("--repeats needs a whole number >= 1");
    } else if (a == "--peer-repeats") {
      if (!number(&peer_repeats)) return Usage("--peer-repeats needs a whole number >= 1");
    } else if (a == "--no-peers") {
      peers = false;
    } else if (a == "--only" && i + 1 < argc) {
      only = argv[++i];
    } else if (a == "--json" && i + 1 < argc) {
      json_path = argv[++i];
    } else {
      return Usage(("unknown or incomplete argument '" + a + "'").c_str());
    }
  }

  irmosaic::SynthOptions sim_options =
      irmosaic::SynthOptions::LoadJson(irmosaic::testing::SamplePath("sample_flight/flight.json"));
  sim_options.frame_count = first + frames;
  irmosaic::FlightSimulator sim(sim_options);

  // 1. The pipeline's pairs, as the Mosaicker registers them.
  std::map<int64_t, irmosaic::OrthoImage> orthos;  // Per frame: a frame is in several pairs.
  std::vector<Pair> pairs;
  std::mutex mu;
  const std::filesystem::path store =
      std::filesystem::temp_directory_path() /
      ("pipeline_pairs_bench_" + std::to_string(::getpid()) + ".irmosaic");
  std::map<int64_t, Eigen::Matrix3d> true_placement;
  {
    irmosaic::MosaickerOptions options;
    options.store_path = store.string();
    options.mode = irmosaic::TileStoreOptions::Mode::kOverwrite;
    options.ground_height_m = sim.options().ground_height_m;
    options.on_pair_registered = [&](const irmosaic::PairRegistrationRecord& record) {
      std::lock_guard<std::mutex> lock(mu);
      if (static_cast<int>(pairs.size()) >= max_pairs) return;
      auto keep = [&](int64_t index, const irmosaic::OrthoImage& ortho) {
        if (orthos.count(index) != 0) return;
        irmosaic::OrthoImage copy;
        copy.image = ortho.image.clone();
        copy.mask = ortho.mask.clone();
        copy.origin_px = ortho.origin_px;
        copy.ortho_from_image = ortho.ortho_from_image;
        orthos.emplace(index, std::move(copy));
      };
      keep(record.base_index, *record.base);
      keep(record.template_index, *record.templ);
      Pair p;
      p.base = record.base_index;
      p.templ = record.template_index;
      p.predicted = record.predicted_offset;
      p.radius = record.search_radius_px;
      p.pipeline_ok = record.result->ok();
      p.pipeline_h = record.result->base_from_template;
      pairs.push_back(p);
    };
    irmosaic::Mosaicker mosaicker(options, sim.camera(), sim.MeasuredPos());
    for (int i = first; i < first + frames; ++i) {
      const irmosaic::SimFrame frame = sim.Render(i);
      true_placement[frame.index] = frame.true_mosaic_from_image;
      mosaicker.Push(frame.index, frame.time_s, frame.image);
      std::lock_guard<std::mutex> lock(mu);
      if (static_cast<int>(pairs.size()) >= max_pairs) break;
    }
    mosaicker.Finish();
  }
  std::error_code ignored;
  std::filesystem::remove_all(store, ignored);
  if (pairs.empty()) {
    std::cerr << "pipeline_pairs_bench: the pipeline registered no pairs in " << frames
              << " frames; give more --frames\n";
    return 1;
  }

  // 2. The truth of each pair.
  for (Pair& p : pairs) {
    const irmosaic::OrthoImage& b = orthos.at(p.base);
    const irmosaic::OrthoImage& t = orthos.at(p.templ);
    p.truth = b.ortho_from_image * true_placement.at(p.base).inverse() *
              true_placement.at(p.templ) * t.ortho_from_image.inverse();
    p.has_overlap = TrueOverlapBox(b, t, p.truth, &p.corners);
    p.frame_corners = ValidBox(t.mask);
  }

  // 3. Each method on every pair, one core.
  cv::setNumThreads(1);
  struct Named {
    std::string name;
    Method method;
    int repeats;
  };
  std::vector<Named> methods = {
      {"pipeline", OursMethod(irmosaic::PipelineRegistrationOptions()), repeats},
      {"defaults", OursMethod(irmosaic::PairRegistrationOptions{}), repeats}};
  {
    // The pipeline's configuration with the FLSM at full resolution (lsm_level 0).
    irmosaic::PairRegistrationOptions level0 = irmosaic::PipelineRegistrationOptions();
    level0.fine.lsm_level = 0;
    methods.insert(methods.begin() + 1, {"lsm-level-0", OursMethod(level0), repeats});
  }
  if (peers) {
    methods.push_back(
        {"ORB+RANSAC", FeatureMethod(cv::ORB::create(2000), cv::NORM_HAMMING), peer_repeats});
    methods.push_back(
        {"SIFT+RANSAC", FeatureMethod(cv::SIFT::create(), cv::NORM_L2), peer_repeats});
  }
  if (!only.empty()) {
    methods.erase(std::remove_if(methods.begin(), methods.end(),
                                 [&](const Named& m) { return m.name != only; }),
                  methods.end());
    if (methods.empty()) return Usage(("--only: no method named '" + only + "'").c_str());
  }
  nlohmann::json out;
  out["frames"] = frames;
  out["pairs"] = pairs.size();
  out["repeats"] = repeats;
  out["peer_repeats"] = peer_repeats;
  out["methods"] = nlohmann::json::array();
  std::printf(
      "\n%zu pairs the pipeline registered in the sample flight's first %d frames "
      "(one core; CPU ms: min of the repeats per pair)\n",
      pairs.size(), frames);
  std::printf("%-12s %8s %8s %8s %8s %8s %8s %8s %9s %9s\n", "method", "accepted", "<=0.3px",
              "<=1px", "med px", "p90 px", "max px", ">1px acc", "CPU ms", "p90 ms");
  double pipeline_ms = 0.0;
  for (const Named& m : methods) {
    std::vector<double> errors, frame_errors, times;
    int accepted = 0, within_03 = 0, within_1 = 0, wrong_accepted = 0;
    double max_vs_pipeline = 0.0;
    nlohmann::json per_pair = nlohmann::json::array();
    for (const Pair& p : pairs) {
      const irmosaic::OrthoImage& b = orthos.at(p.base);
      const irmosaic::OrthoImage& t = orthos.at(p.templ);
      double best = 1e30;
      bool ok = false;
      Eigen::Matrix3d h = Eigen::Matrix3d::Identity();
      nlohmann::json details = nlohmann::json::object();
      for (int r = 0; r < m.repeats; ++r) {
        const double t0 = ThreadCpuMs();
        ok = m.method(b, t, p, &h, &details);
        best = std::min(best, ThreadCpuMs() - t0);
      }
      times.push_back(best);
      double error = std::nan("");
      if (ok && p.has_overlap) {
        ++accepted;
        error = CornerRms(h, p.truth, p.corners);
        errors.push_back(error);
        frame_errors.push_back(CornerRms(h, p.truth, p.frame_corners));
        if (error <= 0.3) ++within_03;
        if (error <= 1.0) ++within_1;
        if (error > 1.0) ++wrong_accepted;
      }
      if (m.name == "pipeline" && ok == p.pipeline_ok && ok && p.has_overlap) {
        max_vs_pipeline = std::max(max_vs_pipeline, CornerRms(h, p.pipeline_h, p.corners));
      }
      nlohmann::json signed_errors = nlohmann::json::array();
      if (ok && p.has_overlap) {
        for (const Eigen::Vector2d& c : p.corners) {
          const Eigen::Vector2d e = Apply(h, c) - Apply(p.truth, c);
          signed_errors.push_back({c.x(), c.y(), e.x(), e.y()});
        }
      }
      per_pair.push_back(
          {{"base", p.base},
           {"template", p.templ},
           {"ok", ok},
           {"corner_errors", signed_errors},
           {"error_px", ok ? nlohmann::json(error) : nlohmann::json(nullptr)},
           {"frame_error_px",
            ok && p.has_overlap ? nlohmann::json(frame_errors.back()) : nlohmann::json(nullptr)},
           {"cpu_ms", best},
           {"details", details}});
    }
    double mean_ms = 0.0;
    for (double t : times) mean_ms += t;
    mean_ms /= static_cast<double>(times.size());
    if (m.name == "pipeline") pipeline_ms = mean_ms;
    std::printf("%-12s %8d %8d %8d %8.3f %8.3f %8.3f %8d %9.2f %9.2f\n", m.name.c_str(), accepted,
                within_03, within_1, Percentile(errors, 0.5), Percentile(errors, 0.9),
                errors.empty() ? std::nan("") : *std::max_element(errors.begin(), errors.end()),
                wrong_accepted, mean_ms, Percentile(times, 0.9));
    std::printf("  %s whole-frame box (extrapolated): median %.3f, p90 %.3f, max %.3f px\n",
                m.name.c_str(), Percentile(frame_errors, 0.5), Percentile(frame_errors, 0.9),
                frame_errors.empty() ? std::nan("")
                                     : *std::max_element(frame_errors.begin(), frame_errors.end()));
    nlohmann::json j = {
        {"method", m.name},
        {"repeats", m.repeats},
        {"accepted", accepted},
        {"within_0_3_px", within_03},
        {"within_1_px", within_1},
        {"accepted_over_1_px", wrong_accepted},
        {"median_error_px", Percentile(errors, 0.5)},
        {"p90_error_px", Percentile(errors, 0.9)},
        {"frame_median_error_px", Percentile(frame_errors, 0.5)},
        {"frame_p90_error_px", Percentile(frame_errors, 0.9)},
        {"frame_max_error_px", frame_errors.empty()
                                   ? std::nan("")
                                   : *std::max_element(frame_errors.begin(), frame_errors.end())},
        {"cpu_ms_per_pair", mean_ms},
        {"p90_cpu_ms", Percentile(times, 0.9)},
        {"per_pair", per_pair}};
    if (m.name == "pipeline") {
      j["max_px_vs_mosaicker"] = max_vs_pipeline;
      std::printf("  (replayed pipeline results against the Mosaicker's own: max %.6f px)\n",
                  max_vs_pipeline);
    }
    out["methods"].push_back(j);
  }
  for (const auto& j : out["methods"]) {
    if (j["method"] != "pipeline" && pipeline_ms > 0) {
      std::printf("%s CPU per pair / pipeline: %.2f\n", j["method"].get<std::string>().c_str(),
                  j["cpu_ms_per_pair"].get<double>() / pipeline_ms);
    }
  }
  std::ofstream(json_path) << out.dump(1) << "\n";
  std::printf("JSON: %s\n", json_path.c_str());
  return 0;
}
