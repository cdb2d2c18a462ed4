#pragma once

#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "irmosaic/camera.h"
#include "irmosaic/export.h"

namespace irmosaic {

// A frame warped onto the mosaic plane, cropped to its footprint's bounding box.
struct OrthoImage {
  cv::Mat image;        // Same type as the input frame.
  cv::Mat mask;         // CV_8U: 255 where the frame has data, 0 elsewhere.
  cv::Point origin_px;  // Mosaic pixel (col, row) of image(0, 0).
  Eigen::Matrix3d ortho_from_image = Eigen::Matrix3d::Identity();  // Undistorted px -> image px.

  bool empty() const { return image.empty(); }
};

struct OrthoOptions {
  int interpolation = cv::INTER_LINEAR;
  int max_side_px = 8192;  // Larger orthoimages are refused (a footprint gone absurd).
  // Frames without lens distortion only: resample just the footprint (plus a 2-pixel margin),
  // in bands of rows, and set the rest of the bounding box to 0, where the default fills it by
  // replicating the frame's border. A rotated oblique footprint covers about half of its box,
  // so this halves the warp; for callers that read the image under the mask only (rendering).
  bool footprint_only = false;
  // 16-bit frames, bilinear, without lens distortion: resampled by irmosaic's own warp
  // (positions exact in float where OpenCV rounds them to 1/32 px; AVX2 where the CPU has it,
  // where OpenCV 4.6 runs scalar code for 16 bits; the same output on every CPU) instead of
  // OpenCV's warpPerspective / warpAffine: 2.1-4.1x faster per orthoimage with AVX2, ~0.7-1x
  // without (bench/ortho_bench). false: OpenCV's.
  bool exact_bilinear_16bit = true;
  // 8-bit frames (video input, `flight_bench --bit-depth 8`), bilinear, without lens distortion:
  // the same own warp (positions exact in float, AVX2 gathers) instead of OpenCV's vector remap
  // of maps rounded to 1/32 px: 1.6-3.3x faster per orthoimage with AVX2 (bench/ortho_bench,
  // session 34). false: OpenCV's.
  bool exact_bilinear_8bit = true;
};

// Warps `frame` (CV_8U, CV_16U or CV_32F, one channel) with the correction homography
// `mosaic_from_image` (undistorted image px -> mosaic px). Lens distortion is undone in the
// same resampling. Throws InputError for an empty or multi-channel frame or an absurd size.
// `image_clip` (undistorted image px, convex; FrameGeometry::image_clip): only that part of the
// frame is warped and unmasked; empty: the whole frame.
IRMOSAIC_EXPORT OrthoImage Orthorectify(const cv::Mat& frame, const CameraModel& camera,
                                        const Eigen::Matrix3d& mosaic_from_image,
                                        const OrthoOptions& options = {},
                                        const std::vector<Eigen::Vector2d>& image_clip = {});

// Reusable scratch space so the hot path allocates nothing once warm.
class IRMOSAIC_EXPORT Orthorectifier {
 public:
  explicit Orthorectifier(CameraModel camera, OrthoOptions options = {});
  // As the free function; `out`'s buffers are reused when sizes allow.
  void Run(const cv::Mat& frame, const Eigen::Matrix3d& mosaic_from_image, OrthoImage* out,
           const std::vector<Eigen::Vector2d>& image_clip = {});
  // On: Run renders into buffers this Orthorectifier keeps, grown to the largest orthoimage
  // so far, and `out`'s image and mask point into them, valid until the next Run (for callers
  // that hand the result on at once). No allocation per frame once warm. Off by default.
  void set_reuse_output(bool on) { reuse_output_ = on; }

 private:
  bool reuse_output_ = false;
  cv::Mat image_backing_, mask_backing_, map_x_backing_, map_y_backing_;
  CameraModel camera_;
  OrthoOptions options_;
  cv::Mat full_mask_;
  cv::Mat map_x_, map_y_;
  std::vector<Eigen::Vector2d> outline_;
};

}  // namespace irmosaic
