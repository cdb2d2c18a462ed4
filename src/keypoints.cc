#include "irmosaic/keypoints.h"

#include <algorithm>
#include <opencv2/imgproc.hpp>

#include "buffer_view.h"
#include "corner_response.h"
#include "irmosaic/error.h"

namespace irmosaic {

bool KeypointOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (grid_cols < 1 || grid_rows < 1 || grid_cols > 256 || grid_rows > 256) {
    return fail("grid_cols and grid_rows must be in [1, 256]");
  }
  if (max_points < 1) return fail("max_points must be >= 1");
  if (!(presmooth_sigma_px >= 0.0 && presmooth_sigma_px <= 20.0)) {
    return fail("presmooth_sigma_px must be in [0, 20]");
  }
  if (block_size < 3 || block_size > 31 || block_size % 2 == 0) {
    return fail("block_size must be odd, in [3, 31]");
  }
  if (!(min_quality >= 0.0 && min_quality < 1.0)) return fail("min_quality must be in [0, 1)");
  if (!(min_distance_px >= 0.0)) return fail("min_distance_px must be >= 0");
  return true;
}

std::vector<Eigen::Vector2d> DetectKeypoints(const cv::Mat& image, const cv::Mat& valid,
                                             const KeypointOptions& options) {
  std::string error;
  if (!options.IsValid(&error)) {
    throw InputError(SourceLocation{"KeypointOptions", 0, 0, ""}, error, "fix the option");
  }
  if (image.empty() || image.channels() != 1 || valid.type() != CV_8UC1 ||
      valid.size() != image.size()) {
    throw InputError(SourceLocation{"DetectKeypoints", 0, 0, ""},
                     "needs a one-channel image and a CV_8U mask of the same size",
                     "convert the image to gray and pass a matching mask");
  }
  const cv::Rect box = cv::boundingRect(valid);
  if (box.empty()) return {};
  // Response over the box plus a margin so the block and blur see real pixels at its edge.
  const int margin = options.block_size + static_cast<int>(3 * options.presmooth_sigma_px) + 1;
  const cv::Rect outer = (box + cv::Size(2 * margin, 2 * margin) - cv::Point(margin, margin)) &
                         cv::Rect(0, 0, image.cols, image.rows);
  // Buffers per thread, grown to the largest window seen: no allocation per call once warm.
  thread_local cv::Mat region_backing, response_backing;
  cv::Mat region = BufferView(&region_backing, outer.size(), CV_32F);
  image(outer).convertTo(region, CV_32F);
  if (options.presmooth_sigma_px > 0) {
    cv::GaussianBlur(region, region, cv::Size(), options.presmooth_sigma_px);
  }
  // cv::cornerMinEigenVal(region, response, block_size, 3), in one pass (src/corner_response.h).
  cv::Mat response = BufferView(&response_backing, outer.size(), CV_32F);
  corner::MinEigenResponse(region, options.block_size, &response);

  struct Candidate {
    float response;
    cv::Point at;
  };
  std::vector<Candidate> winners;
  double strongest = 0.0;
  for (int gy = 0; gy < options.grid_rows; ++gy) {
    for (int gx = 0; gx < options.grid_cols; ++gx) {
      const cv::Rect cell(
          box.x + box.width * gx / options.grid_cols, box.y + box.height * gy / options.grid_rows,
          box.width * (gx + 1) / options.grid_cols - box.width * gx / options.grid_cols,
          box.height * (gy + 1) / options.grid_rows - box.height * gy / options.grid_rows);
      if (cell.empty()) continue;
      const cv::Mat cell_mask = valid(cell);
      if (cv::countNonZero(cell_mask) == 0) continue;
      double best = 0.0;
      cv::Point at;
      cv::minMaxLoc(response(cell - outer.tl()), nullptr, &best, nullptr, &at, cell_mask);
      if (best <= 0.0) continue;
      winners.push_back({static_cast<float>(best), at + cell.tl()});
      strongest = std::max(strongest, best);
    }
  }
  std::sort(winners.begin(), winners.end(),
            [](const Candidate& a, const Candidate& b) { return a.response > b.response; });
  std::vector<Eigen::Vector2d> points;
  const double min_d2 = options.min_distance_px * options.min_distance_px;
  for (const Candidate& c : winners) {
    if (c.response < options.min_quality * strongest) break;
    const Eigen::Vector2d p(c.at.x, c.at.y);
    bool crowded = false;
    for (const Eigen::Vector2d& q : points) crowded |= (p - q).squaredNorm() < min_d2;
    if (crowded) continue;
    points.push_back(p);
    if (static_cast<int>(points.size()) >= options.max_points) break;
  }
  return points;
}

}  // namespace irmosaic
