#pragma once
// Private helper of the simulator (src/simulator.cc, src/ground_texture.cc): bilinear sampling
// of a float image through a projective map, single threaded, for small images rendered many
// times. Not installed.

#include <opencv2/core.hpp>

namespace irmosaic::sim {

// dst(x, y) = src(m (x, y, 1)) (homogeneous), bilinear, sample positions clamped to src (as
// BORDER_REPLICATE); m = src_from_dst. Positions are exact in float (cv::warpPerspective
// quantises them to 1/32 px) and it is 2-4x faster than OpenCV's float path on one core.
void WarpBilinear(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Size size, cv::Mat* dst);

// dst(x, y) += scale * src(m (x, y, 1)), as WarpBilinear; dst is CV_32F, not resized.
void AddWarpBilinear(const cv::Mat& src, const cv::Matx33d& src_from_dst, float scale,
                     cv::Mat* dst);

}  // namespace irmosaic::sim
