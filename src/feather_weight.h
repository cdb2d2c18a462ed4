#pragma once
// Private helper of the map fusion (src/map_fusion.cc): the seam-blending weight of a frame
// without lens distortion, whose footprint on the mosaic is a convex quadrilateral. Not
// installed.

#include <Eigen/Core>
#include <array>
#include <opencv2/core.hpp>

namespace irmosaic::feather {

// weight(x, y) = min(1, max(0, (d + 0.5) / feather_px)) where mask(x, y) is set, 0 elsewhere; d
// is the least signed distance (inward positive) from the pixel to the four edge lines of the
// convex quadrilateral `quad` (pixel coordinates of `mask`, either orientation). The +0.5 matches
// cv::distanceTransform, which measures to the centre of the first pixel outside. mask: CV_8U;
// weight: CV_32F of the mask's size (allocated when needed). Each row is computed over the span
// where the quadrilateral's edge functions can be above zero (zeros elsewhere), with AVX2 where
// the CPU has it and SSE2 otherwise; every output equals WeightScalar's (the same float
// operations in the same order, no fused multiply-add).
void Weight(const std::array<Eigen::Vector2d, 4>& quad, double feather_px, const cv::Mat& mask,
            cv::Mat* weight);

// Tests: the reference, one pixel at a time over whole rows.
void WeightScalar(const std::array<Eigen::Vector2d, 4>& quad, double feather_px,
                  const cv::Mat& mask, cv::Mat* weight);

}  // namespace irmosaic::feather
