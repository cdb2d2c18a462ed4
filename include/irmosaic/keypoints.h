#pragma once

// Key points for fine registration: evenly spread over the valid part of an image (a grid,
// the strongest corner per cell), capped in number, skipping masked and flat areas.

#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "irmosaic/export.h"

namespace irmosaic {

struct KeypointOptions {
  int grid_cols = 8;    // Cells across the bounding box of the valid area.
  int grid_rows = 8;    // Cells down it.
  int max_points = 48;  // Cap: the strongest cell winners are kept.
  // Corner response: minimum eigenvalue of the structure tensor (Shi-Tomasi) over
  // block_size pixels, after a Gaussian pre-blur that keeps sensor noise from ranking.
  double presmooth_sigma_px = 2.0;
  int block_size = 9;
  // A cell winner is dropped when its response is below this fraction of the strongest one
  // (flat areas: sky, water, uniform roofs).
  double min_quality = 0.02;
  // Winners of neighbouring cells closer than this are thinned (pixels).
  double min_distance_px = 10.0;

  // False with a message when an option is out of range.
  bool IsValid(std::string* error) const;
};

// Key points of `image` (one channel, any depth) where `valid` (CV_8U, same size) is
// non-zero; pixel coordinates (integers). Empty when nothing valid or textured remains.
IRMOSAIC_EXPORT std::vector<Eigen::Vector2d> DetectKeypoints(const cv::Mat& image,
                                                             const cv::Mat& valid,
                                                             const KeypointOptions& options = {});

}  // namespace irmosaic
