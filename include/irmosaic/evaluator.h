#pragma once

// Scores a run's frame placements and pairwise registrations against the simulator's truth.
//
// Placements file (JSON), written by `irmosaic synth` (truth.json) and by a run:
//   {"origin": {"lat_deg": .., "lon_deg": ..}, "gsd_m": ..,
//    "frames": [{"index": i, "time_s": t, "mosaic_from_image": [9 numbers, row-major]}, ...]}
// mosaic_from_image maps undistorted image pixels to mosaic pixels of the file's own grid
// (MosaicGrid at gsd_m on the LocalFrame at origin, docs/conventions.md). Two files may have
// different origins and GSDs: the evaluator converts through geodesy.
//
// Pairs file (JSON): {"pairs": [{"base": i, "template": j, "base_from_template": [9]}]}, in
// undistorted image pixels of the two frames.

#include <Eigen/Core>
#include <map>
#include <string>
#include <vector>

#include "irmosaic/camera.h"
#include "irmosaic/export.h"

namespace irmosaic {

// One frame's placement on a mosaic grid.
struct Placement {
  int index = 0;
  double time_s = 0.0;
  Eigen::Matrix3d mosaic_from_image = Eigen::Matrix3d::Identity();
};

// A set of placements with the grid they refer to.
struct IRMOSAIC_EXPORT Placements {
  double origin_lat_deg = 0.0;
  double origin_lon_deg = 0.0;
  double gsd_m = 0.5;
  // Image size the homographies refer to, when the file records it ("image_width",
  // "image_height", optional); 0: unknown.
  int image_width = 0;
  int image_height = 0;
  std::vector<Placement> frames;

  // Reads the JSON format above; throws InputError naming the file and field.
  static Placements LoadJson(const std::string& path);
  // Writes it (full double precision); throws OutputError.
  void SaveJson(const std::string& path) const;
};

// One pairwise registration: base_from_template in undistorted image pixels.
struct PairHomography {
  int base = 0;
  int template_index = 0;
  Eigen::Matrix3d base_from_template = Eigen::Matrix3d::Identity();
};

// Reads the pairs JSON; throws InputError.
IRMOSAIC_EXPORT std::vector<PairHomography> LoadPairsJson(const std::string& path);
// Writes the pairs JSON; throws OutputError.
IRMOSAIC_EXPORT void SavePairsJson(const std::vector<PairHomography>& pairs,
                                   const std::string& path);

struct EvaluatorOptions {
  int grid = 9;  // Points per image side at which placements are compared.
  // Image size the placements refer to; 0: the truth file's image_width/height, else 640x512.
  int width = 0;
  int height = 0;
};

// Summary statistics of a list of errors.
struct ErrorStats {
  int count = 0;
  double mean = 0.0, median = 0.0, p95 = 0.0, max = 0.0, rmse = 0.0;
  double share_within_1px = 0.0;  // Share of items whose error is <= 1 px.
};

// Per frame score.
struct FrameScore {
  int index = 0;
  double rmse_px = 0.0;  // Over the grid, truth mosaic pixels.
  double rmse_m = 0.0;
  double max_px = 0.0;
  Eigen::Vector2d mean_error_m = Eigen::Vector2d::Zero();  // East, north.
};

// A run's placements scored against the truth.
struct PlacementScore {
  std::string name;
  int frames_in_truth = 0;
  int frames_scored = 0;   // Frames present in both.
  int frames_missing = 0;  // In the truth, not placed by the run.
  ErrorStats rmse_px;      // Statistics of the per-frame RMSE (truth pixels).
  ErrorStats rmse_m;
  // Absolute georeference: the mean error vector of all points (east, north, metres) and the
  // RMSE of all points in metres; relative: the RMSE once that mean shift is removed.
  Eigen::Vector2d georeference_offset_m = Eigen::Vector2d::Zero();
  double absolute_rmse_m = 0.0;
  double relative_rmse_px = 0.0;
  std::vector<FrameScore> frames;
};

// Pairwise registrations scored against the truth.
struct PairScore {
  int base = 0, template_index = 0;
  double rmse_px = 0.0;  // Base image pixels, over template grid points inside the base frame.
  int points = 0;
};
struct PairsScore {
  int pairs_given = 0;
  int pairs_scored = 0;  // Both frames in the truth and overlapping.
  ErrorStats rmse_px;
  std::vector<PairScore> pairs;
};

// Scores against a truth; cheap to build, one per truth.
class IRMOSAIC_EXPORT Evaluator {
 public:
  explicit Evaluator(Placements truth, EvaluatorOptions options = {});

  // Per frame: a grid of the frame's pixels placed by the run and by the truth, compared in the
  // truth's mosaic pixels after converting the run's grid through WGS84.
  PlacementScore ScorePlacements(const Placements& run, const std::string& name = "") const;
  // Each pair: template grid points mapped by the given and the true base_from_template.
  PairsScore ScorePairs(const std::vector<PairHomography>& pairs) const;

  const Placements& truth() const { return truth_; }

 private:
  Placements truth_;
  EvaluatorOptions options_;
  std::map<int, size_t> truth_by_index_;
};

// Statistics of a list of values (px); share_within_1px counts values <= 1.
IRMOSAIC_EXPORT ErrorStats ComputeErrorStats(std::vector<double> values);

// The `n` frames of a score with the largest RMSE (px), worst first; frames of equal RMSE by
// index. Fewer when the score holds fewer. Where to look first in a long run.
IRMOSAIC_EXPORT std::vector<FrameScore> WorstFrames(const PlacementScore& score, size_t n = 5);

// Draws RMSE (px, log scale) against frame index, one curve per score, with legend and axes.
IRMOSAIC_EXPORT void PlotRmseVsIndex(const std::vector<PlacementScore>& scores,
                                     const std::string& png_path, const std::string& title = "");

// The scores as JSON text (docs/simulator.md lists the fields).
IRMOSAIC_EXPORT std::string ScoresToJson(const std::vector<PlacementScore>& scores,
                                         const PairsScore* pairs);

}  // namespace irmosaic
