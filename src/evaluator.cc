// Evaluator: a run's placements and pair registrations scored against the truth.
#include "irmosaic/evaluator.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <iomanip>
#include <nlohmann/json.hpp>
#include <sstream>

#include "irmosaic/error.h"
#include "irmosaic/frame_geometry.h"
#include "irmosaic/local_frame.h"

namespace irmosaic {
namespace {

using nlohmann::json;

json ReadJsonFile(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError({path, 0, 0, ""}, "cannot open the file", "check the path");
  try {
    return json::parse(in);
  } catch (const json::parse_error& e) {
    throw InputError({path, 0, 0, ""}, std::string("not valid JSON: ") + e.what(),
                     "fix the JSON syntax");
  } catch (const json::exception& e) {
    // E.g. out_of_range for a number beyond double range ("1e999").
    throw InputError({path, 0, 0, ""}, std::string("not valid JSON: ") + e.what(),
                     "fix the JSON (numbers must fit a double)");
  }
}

double Number(const json& doc, const std::string& key, const std::string& path,
              const std::string& where) {
  if (!doc.is_object() || !doc.contains(key) || !doc.at(key).is_number()) {
    throw InputError({path, 0, 0, where + key}, "missing or non-numeric '" + key + "'",
                     "see the placements format in include/irmosaic/evaluator.h");
  }
  return doc.at(key).get<double>();
}

Eigen::Matrix3d Matrix(const json& doc, const std::string& key, const std::string& path,
                       const std::string& where) {
  if (!doc.contains(key) || !doc.at(key).is_array() || doc.at(key).size() != 9) {
    throw InputError({path, 0, 0, where + key}, "'" + key + "' must be 9 numbers (row-major)",
                     "write the 3x3 homography row by row");
  }
  Eigen::Matrix3d m;
  for (int k = 0; k < 9; ++k) {
    const json& v = doc.at(key)[k];
    m(k / 3, k % 3) = v.is_number() ? v.get<double>() : std::nan("");
  }
  return m;
}

json MatrixJson(const Eigen::Matrix3d& m) {
  json a = json::array();
  for (int k = 0; k < 9; ++k) a.push_back(m(k / 3, k % 3));
  return a;
}

json StatsJson(const ErrorStats& s) {
  return {{"count", s.count},
          {"mean", s.mean},
          {"median", s.median},
          {"p95", s.p95},
          {"max", s.max},
          {"rmse", s.rmse},
          {"share_within_1px", s.share_within_1px}};
}

std::vector<Eigen::Vector2d> ImageGrid(int n, int width, int height) {
  std::vector<Eigen::Vector2d> pts;
  n = std::max(n, 2);
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      pts.emplace_back((width - 1.0) * i / (n - 1), (height - 1.0) * j / (n - 1));
    }
  }
  return pts;
}

}  // namespace

Placements Placements::LoadJson(const std::string& path) {
  const json doc = ReadJsonFile(path);
  Placements p;
  if (!doc.is_object() || !doc.contains("origin")) {
    throw InputError({path, 0, 0, "origin"}, "missing 'origin'",
                     "write \"origin\": {\"lat_deg\": .., \"lon_deg\": ..}");
  }
  p.origin_lat_deg = Number(doc.at("origin"), "lat_deg", path, "origin.");
  p.origin_lon_deg = Number(doc.at("origin"), "lon_deg", path, "origin.");
  p.gsd_m = Number(doc, "gsd_m", path, "");
  if (!(p.gsd_m > 0)) throw InputError({path, 0, 0, "gsd_m"}, "gsd_m must be positive", "fix it");
  if (doc.contains("image_width"))
    p.image_width = static_cast<int>(Number(doc, "image_width", path, ""));
  if (doc.contains("image_height")) {
    p.image_height = static_cast<int>(Number(doc, "image_height", path, ""));
  }
  if (!doc.contains("frames") || !doc.at("frames").is_array()) {
    throw InputError({path, 0, 0, "frames"}, "missing 'frames' array", "add the frames");
  }
  int k = 0;
  for (const json& f : doc.at("frames")) {
    const std::string where = "frames[" + std::to_string(k++) + "].";
    Placement pl;
    pl.index = static_cast<int>(Number(f, "index", path, where));
    pl.time_s =
        f.contains("time_s") && f.at("time_s").is_number() ? f.at("time_s").get<double>() : 0.0;
    pl.mosaic_from_image = Matrix(f, "mosaic_from_image", path, where);
    p.frames.push_back(pl);
  }
  return p;
}

void Placements::SaveJson(const std::string& path) const {
  json frames_json = json::array();
  for (const Placement& f : frames) {
    frames_json.push_back({{"index", f.index},
                           {"time_s", f.time_s},
                           {"mosaic_from_image", MatrixJson(f.mosaic_from_image)}});
  }
  json doc = {{"origin", {{"lat_deg", origin_lat_deg}, {"lon_deg", origin_lon_deg}}},
              {"gsd_m", gsd_m},
              {"frames", frames_json}};
  if (image_width > 0 && image_height > 0) {
    doc["image_width"] = image_width;
    doc["image_height"] = image_height;
  }
  std::ofstream out(path);
  out << std::setprecision(17) << doc.dump(1) << "\n";
  if (!out) throw OutputError("cannot write the placements file " + path);
}

std::vector<PairHomography> LoadPairsJson(const std::string& path) {
  const json doc = ReadJsonFile(path);
  if (!doc.is_object() || !doc.contains("pairs") || !doc.at("pairs").is_array()) {
    throw InputError({path, 0, 0, "pairs"}, "missing 'pairs' array",
                     "write {\"pairs\": [{\"base\": i, \"template\": j, ...}]}");
  }
  std::vector<PairHomography> pairs;
  int k = 0;
  for (const json& p : doc.at("pairs")) {
    const std::string where = "pairs[" + std::to_string(k++) + "].";
    PairHomography r;
    r.base = static_cast<int>(Number(p, "base", path, where));
    r.template_index = static_cast<int>(Number(p, "template", path, where));
    r.base_from_template = Matrix(p, "base_from_template", path, where);
    pairs.push_back(r);
  }
  return pairs;
}

void SavePairsJson(const std::vector<PairHomography>& pairs, const std::string& path) {
  json a = json::array();
  for (const PairHomography& p : pairs) {
    a.push_back({{"base", p.base},
                 {"template", p.template_index},
                 {"base_from_template", MatrixJson(p.base_from_template)}});
  }
  std::ofstream out(path);
  out << json{{"pairs", a}}.dump(1) << "\n";
  if (!out) throw OutputError("cannot write the pairs file " + path);
}

ErrorStats ComputeErrorStats(std::vector<double> values) {
  ErrorStats s;
  s.count = static_cast<int>(values.size());
  if (values.empty()) return s;
  std::sort(values.begin(), values.end());
  double sum = 0, sum_sq = 0;
  int within = 0;
  for (double v : values) {
    sum += v;
    sum_sq += v * v;
    within += v <= 1.0 ? 1 : 0;
  }
  auto quantile = [&](double q) {
    const double pos = q * (values.size() - 1);
    const size_t lo = static_cast<size_t>(std::floor(pos));
    const size_t hi = std::min(lo + 1, values.size() - 1);
    return values[lo] + (pos - lo) * (values[hi] - values[lo]);
  };
  s.mean = sum / s.count;
  s.rmse = std::sqrt(sum_sq / s.count);
  s.median = quantile(0.5);
  s.p95 = quantile(0.95);
  s.max = values.back();
  s.share_within_1px = static_cast<double>(within) / s.count;
  return s;
}

std::vector<FrameScore> WorstFrames(const PlacementScore& score, size_t n) {
  std::vector<FrameScore> worst = score.frames;
  n = std::min(n, worst.size());
  std::partial_sort(worst.begin(), worst.begin() + static_cast<std::ptrdiff_t>(n), worst.end(),
                    [](const FrameScore& a, const FrameScore& b) {
                      return a.rmse_px > b.rmse_px || (a.rmse_px == b.rmse_px && a.index < b.index);
                    });
  worst.resize(n);
  return worst;
}

Evaluator::Evaluator(Placements truth, EvaluatorOptions options)
    : truth_(std::move(truth)), options_(options) {
  if (options_.width <= 0 || options_.height <= 0) {
    const bool known = truth_.image_width > 0 && truth_.image_height > 0;
    options_.width = known ? truth_.image_width : 640;
    options_.height = known ? truth_.image_height : 512;
  }
  for (size_t k = 0; k < truth_.frames.size(); ++k) truth_by_index_[truth_.frames[k].index] = k;
}

PlacementScore Evaluator::ScorePlacements(const Placements& run, const std::string& name) const {
  PlacementScore score;
  score.name = name;
  score.frames_in_truth = static_cast<int>(truth_.frames.size());
  const LocalFrame truth_frame(truth_.origin_lat_deg, truth_.origin_lon_deg);
  const LocalFrame run_frame(run.origin_lat_deg, run.origin_lon_deg);
  PlaneToGeographic run_to_geographic(run_frame);
  const MosaicGrid truth_grid{truth_.gsd_m}, run_grid{run.gsd_m};
  const bool same_grid = run.origin_lat_deg == truth_.origin_lat_deg &&
                         run.origin_lon_deg == truth_.origin_lon_deg && run.gsd_m == truth_.gsd_m;
  const std::vector<Eigen::Vector2d> grid =
      ImageGrid(options_.grid, options_.width, options_.height);

  std::vector<double> frame_rmse_px, frame_rmse_m;
  std::vector<Eigen::Vector2d> all_errors_px;
  std::map<int, bool> placed;
  for (const Placement& f : run.frames) {
    const auto it = truth_by_index_.find(f.index);
    if (it == truth_by_index_.end() || placed.count(f.index)) continue;
    if (!f.mosaic_from_image.allFinite()) continue;
    placed[f.index] = true;
    const Eigen::Matrix3d& h_true = truth_.frames[it->second].mosaic_from_image;
    FrameScore fs;
    fs.index = f.index;
    double sum_sq = 0.0;
    Eigen::Vector2d sum = Eigen::Vector2d::Zero();
    for (const Eigen::Vector2d& u : grid) {
      Eigen::Vector2d in_truth = ApplyHomography(f.mosaic_from_image, u);
      if (!same_grid) {
        const Eigen::Vector2d lat_lon =
            run_to_geographic.LatLonFromPlane(run_grid.PlaneFromPixel(in_truth));
        in_truth =
            truth_grid.PixelFromPlane(truth_frame.PlaneFromGeodetic(lat_lon.x(), lat_lon.y()));
      }
      Eigen::Vector2d e = in_truth - ApplyHomography(h_true, u);
      if (!e.allFinite()) e = Eigen::Vector2d(1e9, 1e9);  // A degenerate placement: far off.
      sum_sq += e.squaredNorm();
      sum += e;
      fs.max_px = std::max(fs.max_px, e.norm());
      all_errors_px.push_back(e);
    }
    fs.rmse_px = std::sqrt(sum_sq / grid.size());
    fs.rmse_m = fs.rmse_px * truth_.gsd_m;
    const Eigen::Vector2d mean_px = sum / static_cast<double>(grid.size());
    fs.mean_error_m = {mean_px.x() * truth_.gsd_m, -mean_px.y() * truth_.gsd_m};
    frame_rmse_px.push_back(fs.rmse_px);
    frame_rmse_m.push_back(fs.rmse_m);
    score.frames.push_back(fs);
  }
  std::sort(score.frames.begin(), score.frames.end(),
            [](const FrameScore& a, const FrameScore& b) { return a.index < b.index; });
  score.frames_scored = static_cast<int>(score.frames.size());
  score.frames_missing = score.frames_in_truth - score.frames_scored;
  score.rmse_px = ComputeErrorStats(frame_rmse_px);
  score.rmse_m = ComputeErrorStats(frame_rmse_m);
  // rmse_m's "within 1 px" share is about metres; restate it in pixels for clarity.
  score.rmse_m.share_within_1px = score.rmse_px.share_within_1px;
  if (!all_errors_px.empty()) {
    Eigen::Vector2d mean = Eigen::Vector2d::Zero();
    double sum_sq = 0.0;
    for (const auto& e : all_errors_px) {
      mean += e;
      sum_sq += e.squaredNorm();
    }
    mean /= static_cast<double>(all_errors_px.size());
    double rel_sq = 0.0;
    for (const auto& e : all_errors_px) rel_sq += (e - mean).squaredNorm();
    score.georeference_offset_m = {mean.x() * truth_.gsd_m, -mean.y() * truth_.gsd_m};
    score.absolute_rmse_m = std::sqrt(sum_sq / all_errors_px.size()) * truth_.gsd_m;
    score.relative_rmse_px = std::sqrt(rel_sq / all_errors_px.size());
  }
  return score;
}

PairsScore Evaluator::ScorePairs(const std::vector<PairHomography>& pairs) const {
  PairsScore score;
  score.pairs_given = static_cast<int>(pairs.size());
  const std::vector<Eigen::Vector2d> grid =
      ImageGrid(options_.grid, options_.width, options_.height);
  std::vector<double> values;
  for (const PairHomography& p : pairs) {
    const auto b = truth_by_index_.find(p.base);
    const auto t = truth_by_index_.find(p.template_index);
    if (b == truth_by_index_.end() || t == truth_by_index_.end()) continue;
    const Eigen::Matrix3d truth_bt = truth_.frames[b->second].mosaic_from_image.inverse() *
                                     truth_.frames[t->second].mosaic_from_image;
    PairScore ps;
    ps.base = p.base;
    ps.template_index = p.template_index;
    double sum_sq = 0.0;
    for (const Eigen::Vector2d& u : grid) {
      const Eigen::Vector2d q = ApplyHomography(truth_bt, u);
      // Only the overlap counts: outside it a registration is an extrapolation.
      if (q.x() < -0.5 || q.y() < -0.5 || q.x() > options_.width - 0.5 ||
          q.y() > options_.height - 0.5) {
        continue;
      }
      Eigen::Vector2d e = ApplyHomography(p.base_from_template, u) - q;
      if (!e.allFinite()) e = Eigen::Vector2d(1e9, 1e9);
      sum_sq += e.squaredNorm();
      ++ps.points;
    }
    if (ps.points == 0) continue;
    ps.rmse_px = std::sqrt(sum_sq / ps.points);
    values.push_back(ps.rmse_px);
    score.pairs.push_back(ps);
  }
  score.pairs_scored = static_cast<int>(score.pairs.size());
  score.rmse_px = ComputeErrorStats(values);
  return score;
}

std::string ScoresToJson(const std::vector<PlacementScore>& scores, const PairsScore* pairs) {
  json runs = json::array();
  for (const PlacementScore& s : scores) {
    json frames = json::array();
    for (const FrameScore& f : s.frames) {
      frames.push_back({{"index", f.index},
                        {"rmse_px", f.rmse_px},
                        {"rmse_m", f.rmse_m},
                        {"max_px", f.max_px},
                        {"mean_error_m", {f.mean_error_m.x(), f.mean_error_m.y()}}});
    }
    runs.push_back(
        {{"name", s.name},
         {"frames_in_truth", s.frames_in_truth},
         {"frames_scored", s.frames_scored},
         {"frames_missing", s.frames_missing},
         {"rmse_px", StatsJson(s.rmse_px)},
         {"rmse_m", StatsJson(s.rmse_m)},
         {"georeference_offset_m", {s.georeference_offset_m.x(), s.georeference_offset_m.y()}},
         {"absolute_rmse_m", s.absolute_rmse_m},
         {"relative_rmse_px", s.relative_rmse_px},
         {"frames", frames}});
  }
  json doc = {{"runs", runs}};
  if (pairs != nullptr) {
    json list = json::array();
    for (const PairScore& p : pairs->pairs) {
      list.push_back({{"base", p.base},
                      {"template", p.template_index},
                      {"rmse_px", p.rmse_px},
                      {"points", p.points}});
    }
    doc["pairs"] = {{"pairs_given", pairs->pairs_given},
                    {"pairs_scored", pairs->pairs_scored},
                    {"rmse_px", StatsJson(pairs->rmse_px)},
                    {"pairs", list}};
  }
  return doc.dump(1);
}

}  // namespace irmosaic
