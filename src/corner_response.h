#pragma once
// Private helper of the key-point detector (src/keypoints.cc): the Shi-Tomasi corner response
// (the smaller eigenvalue of the structure tensor summed over a block), what
// cv::cornerMinEigenVal(src, dst, block_size, 3) computes, in one pass over the image with
// buffers kept per thread. OpenCV's makes five passes with five image-sized allocations (the two
// Sobel images, the 3-channel products, their box filter, the response); in the pipeline's pair
// registration it was 81 % of the detector's time (docs/benchmarks.md, "Session 46"). Not
// installed.

#include <opencv2/core.hpp>

namespace irmosaic::corner {

// response (CV_32F, src's size, allocated when needed) = the smaller eigenvalue of
// [Sxx Sxy; Sxy Syy] / 2 where Sxx, Sxy, Syy are the sums over a block_size x block_size block of
// dx^2, dx dy, dy^2, and dx, dy the 3x3 Sobel derivatives scaled by 1 / (4 block_size), borders
// reflected without repeating the edge pixel (OpenCV's BORDER_REFLECT_101): the definition of
// cv::cornerMinEigenVal with aperture 3 for float input. Sums in float (OpenCV's box filter sums
// in double): the two agree to ~1e-6 of the image's largest response
// (tests/corner_response_test.cc). src: CV_32F, one channel; block_size odd, >= 3. Images smaller
// than block_size + 2 on a side go to cv::cornerMinEigenVal itself.
void MinEigenResponse(const cv::Mat& src, int block_size, cv::Mat* response);

}  // namespace irmosaic::corner
