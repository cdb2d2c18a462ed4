#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

#include "irmosaic/export.h"

namespace irmosaic {

// Pinhole camera with OpenCV distortion, mounted with a boresight rotation and a lever arm.
// Camera axes are OpenCV's: x right, y down, z along the optical axis (docs/conventions.md).
struct IRMOSAIC_EXPORT CameraModel {
  int width = 640;
  int height = 512;
  double fx = 0.0;  // Focal length in pixels.
  double fy = 0.0;
  double cx = 0.0;  // Principal point, pixels, origin at the centre of the top-left pixel.
  double cy = 0.0;
  // OpenCV order k1, k2, p1, p2[, k3[, k4, k5, k6]]; empty means no distortion.
  std::vector<double> distortion;
  // Small rotation of the camera relative to its nominal mounting, degrees: angles about the
  // camera's own x, y, z axes, composed as Rz * Ry * Rx (docs/conventions.md).
  Eigen::Vector3d boresight_deg = Eigen::Vector3d::Zero();
  // Camera centre relative to the POS reference point, in aircraft body axes, metres.
  Eigen::Vector3d lever_arm_m = Eigen::Vector3d::Zero();

  // Reads the JSON camera file of docs/formats.md. Throws InputError naming file and field.
  static CameraModel LoadJson(const std::string& path);
  // Writes the JSON camera file.
  void SaveJson(const std::string& path) const;
  // Throws InputError naming `source` and the first bad field.
  void Validate(const std::string& source) const;

  bool HasDistortion() const;
  // Pixel (distorted, as recorded) to an undistorted pixel of the same pinhole camera.
  Eigen::Vector2d Undistort(const Eigen::Vector2d& pixel) const;
  // Undistorted pixel to the recorded, distorted pixel.
  Eigen::Vector2d Distort(const Eigen::Vector2d& pixel) const;
  // Unit ray in camera axes through an undistorted pixel.
  Eigen::Vector3d RayThroughPixel(const Eigen::Vector2d& undistorted_pixel) const;

  // Rotation from camera axes to the mount axes: nominal mounting (camera looks along the
  // mount's +z, image top toward the mount's +x) times the boresight rotation.
  Eigen::Quaterniond MountFromCamera() const;
};

// A camera with the project's default sensor: 640x512, long focal length, no distortion.
IRMOSAIC_EXPORT CameraModel DefaultInfraredCamera(double fx_px = 2400.0);

}  // namespace irmosaic
