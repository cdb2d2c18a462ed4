#pragma once

#include <Eigen/Core>
#include <array>
#include <string>
#include <vector>

#include "irmosaic/camera.h"
#include "irmosaic/export.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/pos.h"

namespace irmosaic {

// Height of the ground above the WGS84 ellipsoid. An interface so a DEM can replace the
// constant-height ground without touching the geometry.
class IRMOSAIC_EXPORT GroundModel {
 public:
  virtual ~GroundModel() = default;
  // Ellipsoidal height (m) of the ground at a position.
  virtual double HeightAt(double lat_deg, double lon_deg) const = 0;
};

// Ground at one ellipsoidal height everywhere.
class IRMOSAIC_EXPORT FlatGround : public GroundModel {
 public:
  explicit FlatGround(double height_m = 0.0) : height_m_(height_m) {}
  double HeightAt(double, double) const override { return height_m_; }

 private:
  double height_m_;
};

// Where a pixel's ray meets the ground.
struct RayHit {
  enum class Status { kOk, kAboveHorizon, kBeyondRange, kCameraBelowGround };
  Status status = Status::kOk;
  Eigen::Vector3d geodetic = Eigen::Vector3d::Zero();  // lat_deg, lon_deg, height_m
  double range_m = 0.0;                                // Camera to ground along the ray.

  bool ok() const { return status == Status::kOk; }
};

// Camera centre and axes of a frame in ECEF (metres), from its pose and the camera model.
struct CameraInEcef {
  Eigen::Vector3d position;
  Eigen::Matrix3d ecef_from_camera;
};
IRMOSAIC_EXPORT CameraInEcef LocateCamera(const CameraModel& camera, const Pose& pose);

// Intersects the ray through an undistorted pixel with the ground (exact on the ellipsoid
// surface at the ground height, by GeographicLib; no planar approximation).
IRMOSAIC_EXPORT RayHit IntersectGround(const CameraModel& camera, const CameraInEcef& located,
                                       const Eigen::Vector2d& undistorted_pixel,
                                       const GroundModel& ground, double max_range_m);

struct GeometryOptions {
  // Ground farther than this from the camera is clipped off the frame, with a warning (a
  // grazing view would otherwise paint an absurdly large footprint); a frame with too little
  // ground within it is refused.
  double max_range_m = 30000.0;
  int fit_grid = 9;  // Ray samples per image side for the homography fit.
};

// One frame's place on the mosaic plane.
struct FrameGeometry {
  bool ok = false;
  std::string problem;  // Why not ok: e.g. a corner ray at or above the horizon.
  // Homography from undistorted image pixels to mosaic pixels (see MosaicGrid).
  Eigen::Matrix3d mosaic_from_image = Eigen::Matrix3d::Identity();
  // Image corners (outer pixel edges TL, TR, BR, BL) on the mosaic plane, metres.
  std::array<Eigen::Vector2d, 4> footprint_m;
  double fit_rms_px = 0.0;  // Homography fit against the exact rays, mosaic pixels.
  double fit_max_px = 0.0;
  // When ground beyond max_range_m was clipped: the part of the frame kept, a convex polygon in
  // undistorted image pixels (the homography is fitted on it and footprint_m lies in it);
  // empty: the whole frame. `warning` then says so, `kept_fraction` is its share of the frame.
  std::vector<Eigen::Vector2d> image_clip;
  double kept_fraction = 1.0;
  std::string warning;
};

// Correction homography of a frame: rays of a grid of pixels meet the ground exactly; the
// homography is the least-squares fit (normalized DLT) of image to mosaic pixels.
IRMOSAIC_EXPORT FrameGeometry ComputeFrameGeometry(const CameraModel& camera, const Pose& pose,
                                                   const LocalFrame& frame, const MosaicGrid& grid,
                                                   const GroundModel& ground,
                                                   const GeometryOptions& options = {});

// How POS errors move a frame on the mosaic: the square-root information matrix L (10x10) of
// the frame's four corners and centre (mosaic px, order TL, TR, BR, BL, centre; x then y),
// from the Jacobian J of those points with respect to position (east, north, up) and attitude
// (roll, pitch, yaw) by central differences: covariance J S J^T + model_sigma_px^2 I, with S the
// diagonal POS variances. A prior residual L * (points - POS points) is then whitened.
IRMOSAIC_EXPORT Eigen::Matrix<double, 10, 10> PosPriorSqrtInformation(
    const CameraModel& camera, const Pose& pose, const LocalFrame& frame, const MosaicGrid& grid,
    const GroundModel& ground, double position_sigma_m, double attitude_sigma_deg,
    double model_sigma_px);

// Normalized DLT homography from >= 4 correspondences (least squares for more).
IRMOSAIC_EXPORT Eigen::Matrix3d FitHomography(const std::vector<Eigen::Vector2d>& from,
                                              const std::vector<Eigen::Vector2d>& to);

// Applies a homography to a point.
inline Eigen::Vector2d ApplyHomography(const Eigen::Matrix3d& h, const Eigen::Vector2d& p) {
  const Eigen::Vector3d q = h * p.homogeneous();
  return q.hnormalized();
}

}  // namespace irmosaic
