#include "irmosaic/orthorectify.h"

#include <array>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <utility>

#include "buffer_view.h"
#include "irmosaic/error.h"
#include "irmosaic/frame_geometry.h"
#include "warp_bilinear.h"

namespace irmosaic {

Orthorectifier::Orthorectifier(CameraModel camera, OrthoOptions options)
    : camera_(std::move(camera)), options_(options) {}

namespace {

// Zeroes `mask` outside the clip polygon (undistorted image px) mapped by ortho_from_image.
void ApplyClip(const std::vector<Eigen::Vector2d>& image_clip,
               const Eigen::Matrix3d& ortho_from_image, cv::Mat* mask) {
  if (image_clip.empty()) return;
  constexpr int kShift = 4;
  std::vector<cv::Point> polygon;
  for (const Eigen::Vector2d& p : image_clip) {
    const Eigen::Vector2d q = ApplyHomography(ortho_from_image, p);
    polygon.emplace_back(static_cast<int>(std::lround(q.x() * (1 << kShift))),
                         static_cast<int>(std::lround(q.y() * (1 << kShift))));
  }
  cv::Mat keep(mask->size(), CV_8U, cv::Scalar(0));
  cv::fillConvexPoly(keep, polygon.data(), static_cast<int>(polygon.size()), cv::Scalar(255),
                     cv::LINE_8, kShift);
  cv::bitwise_and(*mask, keep, *mask);
}

// x-range [x0, x1) of the convex polygon `poly` between rows y0 and y1 (inclusive, pixel
// centres), grown by `margin` and clamped to [0, width); empty (x0 >= x1) when they do not meet.
// Sutherland-Hodgman against the two horizontal half-planes.
std::pair<int, int> PolygonSpan(const std::array<Eigen::Vector2d, 4>& poly, double y0, double y1,
                                double margin, int width) {
  double lo = INFINITY, hi = -INFINITY;
  const double top = y0 - margin, bottom = y1 + margin;
  for (size_t k = 0; k < poly.size(); ++k) {
    const Eigen::Vector2d& a = poly[k];
    const Eigen::Vector2d& b = poly[(k + 1) % poly.size()];
    // The part of edge a-b inside [top, bottom], if any.
    double t0 = 0.0, t1 = 1.0;
    const double dy = b.y() - a.y();
    if (dy == 0.0) {
      if (a.y() < top || a.y() > bottom) continue;
    } else {
      double ta = (top - a.y()) / dy, tb = (bottom - a.y()) / dy;
      if (ta > tb) std::swap(ta, tb);
      t0 = std::max(t0, ta);
      t1 = std::min(t1, tb);
      if (t0 > t1) continue;
    }
    for (const double t : {t0, t1}) {
      const double x = a.x() + t * (b.x() - a.x());
      lo = std::min(lo, x);
      hi = std::max(hi, x);
    }
  }
  if (!(lo <= hi)) return {0, 0};
  const int x0 = std::max(0, static_cast<int>(std::floor(lo - margin)));
  const int x1 = std::min(width, static_cast<int>(std::ceil(hi + margin)) + 1);
  return {x0, std::max(x0, x1)};
}

}  // namespace

void Orthorectifier::Run(const cv::Mat& frame, const Eigen::Matrix3d& mosaic_from_image,
                         OrthoImage* out, const std::vector<Eigen::Vector2d>& image_clip) {
  if (frame.empty() || frame.channels() != 1 ||
      (frame.depth() != CV_8U && frame.depth() != CV_16U && frame.depth() != CV_32F)) {
    throw InputError({"frame", 0, 0, ""},
                     "orthorectification needs a one-channel 8-bit, "
                     "16-bit or float image",
                     "convert the frame to grayscale");
  }
  if (!mosaic_from_image.allFinite()) {
    throw InputError({"frame", 0, 0, ""}, "the correction homography is not finite",
                     "check the frame's pose");
  }
  // Bounding box of the footprint: outer pixel edges sampled along each side (distortion
  // can bow the sides outward).
  const double w = frame.cols, h = frame.rows;
  double min_x = INFINITY, min_y = INFINITY, max_x = -INFINITY, max_y = -INFINITY;
  constexpr int kSamples = 8;
  // The outline to bound: the frame's outer edges (raw px, undistorted), or the clip polygon.
  std::vector<Eigen::Vector2d>& outline = outline_;  // Reused: no allocation once warm.
  outline.assign(image_clip.begin(), image_clip.end());
  if (outline.empty()) {
    for (int s = 0; s <= kSamples; ++s) {
      const double f = static_cast<double>(s) / kSamples;
      for (const Eigen::Vector2d& raw :
           {Eigen::Vector2d(-0.5 + f * w, -0.5), Eigen::Vector2d(-0.5 + f * w, h - 0.5),
            Eigen::Vector2d(-0.5, -0.5 + f * h), Eigen::Vector2d(w - 0.5, -0.5 + f * h)}) {
        outline.push_back(camera_.Undistort(raw));
      }
    }
  }
  {
    for (const Eigen::Vector2d& undistorted : outline) {
      const Eigen::Vector3d q = mosaic_from_image * undistorted.homogeneous();
      if (q.z() <= 0.0) {
        throw InputError({"frame", 0, 0, ""}, "the frame's footprint crosses the horizon",
                         "check the pose; frames looking at the sky cannot be mapped");
      }
      const Eigen::Vector2d p = q.hnormalized();
      min_x = std::min(min_x, p.x());
      max_x = std::max(max_x, p.x());
      min_y = std::min(min_y, p.y());
      max_y = std::max(max_y, p.y());
    }
  }
  const int x0 = static_cast<int>(std::floor(min_x)), y0 = static_cast<int>(std::floor(min_y));
  const double width = std::ceil(max_x) - x0 + 1, height = std::ceil(max_y) - y0 + 1;
  if (!(width <= options_.max_side_px && height <= options_.max_side_px)) {
    std::ostringstream problem;
    problem << "the orthoimage would be " << width << " x " << height << " pixels";
    throw InputError({"frame", 0, 0, ""}, problem.str(),
                     "raise the ground sample distance or the size limit, or check the pose");
  }
  const cv::Size size(static_cast<int>(width), static_cast<int>(height));
  if (reuse_output_) {
    out->image = BufferView(&image_backing_, size, frame.type());
    out->mask = BufferView(&mask_backing_, size, CV_8U);
  }
  Eigen::Matrix3d shift = Eigen::Matrix3d::Identity();
  shift(0, 2) = -x0;
  shift(1, 2) = -y0;
  out->origin_px = {x0, y0};
  out->ortho_from_image = shift * mosaic_from_image;
  cv::Matx33d image_from_ortho;
  const Eigen::Matrix3d inverse = out->ortho_from_image.inverse();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) image_from_ortho(r, c) = inverse(r, c);

  if (!camera_.HasDistortion()) {
    // Near nadir the homography is affine to a hundredth of a pixel over the orthoimage, and
    // warpAffine costs about half of warpPerspective: use it when the difference is below
    // kAffineTolerancePx at the orthoimage's corners and centre.
    constexpr double kAffineTolerancePx = 0.01;
    const Eigen::Matrix3d& inv = inverse;
    const Eigen::Vector2d centre(size.width / 2.0, size.height / 2.0);
    const Eigen::Vector3d at_centre = inv * centre.homogeneous();
    // Affine map tangent to the homography at the centre.
    Eigen::Matrix<double, 2, 3> affine;
    const double scale = at_centre.z();
    for (int r = 0; r < 2; ++r) {
      for (int k = 0; k < 2; ++k) {
        affine(r, k) = (inv(r, k) - at_centre(r) / scale * inv(2, k)) / scale;
      }
      affine(r, 2) = at_centre(r) / scale - affine(r, 0) * centre.x() - affine(r, 1) * centre.y();
    }
    double worst = 0.0;
    for (const Eigen::Vector2d& p :
         {Eigen::Vector2d(0, 0), Eigen::Vector2d(size.width, 0), Eigen::Vector2d(0, size.height),
          Eigen::Vector2d(size.width, size.height)}) {
      worst = std::max(worst, (ApplyHomography(inv, p) - affine * p.homogeneous()).norm());
    }
    const bool use_affine = worst < kAffineTolerancePx;
    const cv::Matx23d m(affine(0, 0), affine(0, 1), affine(0, 2), affine(1, 0), affine(1, 1),
                        affine(1, 2));
    // Without distortion the footprint is the quadrilateral of the outer pixel edges.
    const std::array<Eigen::Vector2d, 4> corners = {
        Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(w - 0.5, -0.5),
        Eigen::Vector2d(w - 0.5, h - 0.5), Eigen::Vector2d(-0.5, h - 0.5)};
    std::array<Eigen::Vector2d, 4> footprint;
    for (int c = 0; c < 4; ++c) footprint[c] = ApplyHomography(out->ortho_from_image, corners[c]);
    // OrthoOptions::exact_bilinear_16bit / _8bit: the own warp, where it takes the frame.
    const bool own_warp = options_.interpolation == cv::INTER_LINEAR &&
                          ((options_.exact_bilinear_16bit && frame.type() == CV_16UC1) ||
                           (options_.exact_bilinear_8bit && frame.type() == CV_8UC1));
    if (!options_.footprint_only && own_warp) {
      out->image.create(size, frame.type());
      warp::WarpBilinear(frame, image_from_ortho, &out->image);
    } else if (!options_.footprint_only) {
      if (use_affine) {
        cv::warpAffine(frame, out->image, m, size, options_.interpolation | cv::WARP_INVERSE_MAP,
                       cv::BORDER_REPLICATE);
      } else {
        cv::warpPerspective(frame, out->image, image_from_ortho, size,
                            options_.interpolation | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
      }
    } else {
      // Bands of rows, each warped over the footprint's span in it: the maps shifted by the
      // band's corner (x0, y0), since OpenCV's warps write from the destination's (0, 0).
      out->image.create(size, frame.type());
      constexpr int kBandRows = 32;
      constexpr double kMarginPx = 2.0;
      for (int band_y0 = 0; band_y0 < size.height; band_y0 += kBandRows) {
        const int band_y1 = std::min(size.height, band_y0 + kBandRows);
        const auto [band_x0, band_x1] =
            PolygonSpan(footprint, band_y0, band_y1 - 1, kMarginPx, size.width);
        cv::Mat band = out->image.rowRange(band_y0, band_y1);
        if (band_x0 >= band_x1) {
          band.setTo(0);
          continue;
        }
        if (band_x0 > 0) band.colRange(0, band_x0).setTo(0);
        if (band_x1 < size.width) band.colRange(band_x1, size.width).setTo(0);
        cv::Mat part = band.colRange(band_x0, band_x1);
        const double sx = band_x0, sy = band_y0;
        if (own_warp) {
          const cv::Matx33d band_shift(1, 0, sx, 0, 1, sy, 0, 0, 1);
          warp::WarpBilinear(frame, image_from_ortho * band_shift, &part);
        } else if (use_affine) {
          cv::Matx23d shifted = m;
          shifted(0, 2) += m(0, 0) * sx + m(0, 1) * sy;
          shifted(1, 2) += m(1, 0) * sx + m(1, 1) * sy;
          cv::warpAffine(frame, part, shifted, part.size(),
                         options_.interpolation | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
        } else {
          const cv::Matx33d band_shift(1, 0, sx, 0, 1, sy, 0, 0, 1);
          cv::warpPerspective(frame, part, image_from_ortho * band_shift, part.size(),
                              options_.interpolation | cv::WARP_INVERSE_MAP, cv::BORDER_REPLICATE);
        }
      }
    }
    // Filling the quadrilateral (sub-pixel vertices) costs a fraction of a second warp.
    out->mask.create(size, CV_8U);
    out->mask.setTo(0);
    constexpr int kShift = 4;
    std::array<cv::Point, 4> quad;
    for (int c = 0; c < 4; ++c) {
      const Eigen::Vector2d& p = footprint[c];
      quad[c] = cv::Point(static_cast<int>(std::lround(p.x() * (1 << kShift))),
                          static_cast<int>(std::lround(p.y() * (1 << kShift))));
    }
    cv::fillConvexPoly(out->mask, quad.data(), 4, cv::Scalar(255), cv::LINE_8, kShift);
    ApplyClip(image_clip, out->ortho_from_image, &out->mask);
    return;
  }
  // With distortion: ortho px -> undistorted px (homography) -> recorded px (lens model).
  std::vector<cv::Point3d> rays(static_cast<size_t>(size.area()));
  for (int y = 0; y < size.height; ++y) {
    for (int x = 0; x < size.width; ++x) {
      const cv::Vec3d q = image_from_ortho * cv::Vec3d(x, y, 1.0);
      rays[static_cast<size_t>(y) * size.width + x] = {
          (q[0] / q[2] - camera_.cx) / camera_.fx, (q[1] / q[2] - camera_.cy) / camera_.fy, 1.0};
    }
  }
  std::vector<cv::Point2d> pixels;
  const cv::Matx33d k(camera_.fx, 0, camera_.cx, 0, camera_.fy, camera_.cy, 0, 0, 1);
  cv::projectPoints(rays, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), k, camera_.distortion, pixels);
  map_x_ = BufferView(&map_x_backing_, size, CV_32F);
  map_y_ = BufferView(&map_y_backing_, size, CV_32F);
  for (int y = 0; y < size.height; ++y) {
    for (int x = 0; x < size.width; ++x) {
      const cv::Point2d& p = pixels[static_cast<size_t>(y) * size.width + x];
      map_x_.at<float>(y, x) = static_cast<float>(p.x);
      map_y_.at<float>(y, x) = static_cast<float>(p.y);
    }
  }
  cv::remap(frame, out->image, map_x_, map_y_, options_.interpolation, cv::BORDER_REPLICATE);
  if (full_mask_.size() != frame.size()) full_mask_ = cv::Mat(frame.size(), CV_8U, 255);
  cv::remap(full_mask_, out->mask, map_x_, map_y_, cv::INTER_NEAREST, cv::BORDER_CONSTANT, 0);
  ApplyClip(image_clip, out->ortho_from_image, &out->mask);
}

OrthoImage Orthorectify(const cv::Mat& frame, const CameraModel& camera,
                        const Eigen::Matrix3d& mosaic_from_image, const OrthoOptions& options,
                        const std::vector<Eigen::Vector2d>& image_clip) {
  Orthorectifier worker(camera, options);
  OrthoImage out;
  worker.Run(frame, mosaic_from_image, &out, image_clip);
  return out;
}

}  // namespace irmosaic
