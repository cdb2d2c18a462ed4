#include "irmosaic/frame_geometry.h"

#include <Eigen/SVD>
#include <GeographicLib/Geocentric.hpp>
#include <cmath>
#include <sstream>

namespace irmosaic {
namespace {

const GeographicLib::Geocentric& Earth() { return GeographicLib::Geocentric::WGS84(); }

// ENU axes and NED axes at a point: NED = (north, east, down).
Eigen::Matrix3d EnuFromNed() {
  Eigen::Matrix3d m;
  m << 0, 1, 0, 1, 0, 0, 0, 0, -1;
  return m;
}

// Smallest positive t where the ray meets the ellipsoid inflated by `h` (an initial guess).
bool InflatedEllipsoidHit(const Eigen::Vector3d& p, const Eigen::Vector3d& d, double h, double* t) {
  const double a = Earth().EquatorialRadius() + h;
  const double b = Earth().EquatorialRadius() * (1.0 - Earth().Flattening()) + h;
  const Eigen::Vector3d s(1.0 / a, 1.0 / a, 1.0 / b);
  const Eigen::Vector3d ps = p.cwiseProduct(s), ds = d.cwiseProduct(s);
  const double qa = ds.squaredNorm(), qb = 2.0 * ps.dot(ds), qc = ps.squaredNorm() - 1.0;
  const double disc = qb * qb - 4.0 * qa * qc;
  if (disc < 0.0) return false;
  const double root = (-qb - std::sqrt(disc)) / (2.0 * qa);
  if (root <= 0.0) return false;
  *t = root;
  return true;
}

// Height of a point above the ground (m), and its geodetic coordinates.
double HeightAboveGround(const Eigen::Vector3d& ecef, const GroundModel& ground,
                         Eigen::Vector3d* geodetic) {
  double lat = 0, lon = 0, h = 0;
  Earth().Reverse(ecef.x(), ecef.y(), ecef.z(), lat, lon, h);
  *geodetic = {lat, lon, h};
  return h - ground.HeightAt(lat, lon);
}

}  // namespace

CameraInEcef LocateCamera(const CameraModel& camera, const Pose& pose) {
  double x = 0, y = 0, z = 0;
  std::vector<double> rotation(9);
  Earth().Forward(pose.lat_deg, pose.lon_deg, pose.height_m, x, y, z, rotation);
  // GeographicLib returns the ENU-to-ECEF rotation in row-major order.
  const Eigen::Matrix3d ecef_from_enu =
      Eigen::Map<const Eigen::Matrix<double, 3, 3, Eigen::RowMajor>>(rotation.data());
  const Eigen::Matrix3d ecef_from_body =
      ecef_from_enu * EnuFromNed() * pose.ned_from_body.toRotationMatrix();
  CameraInEcef located;
  located.position = Eigen::Vector3d(x, y, z) + ecef_from_body * camera.lever_arm_m;
  located.ecef_from_camera = ecef_from_body * pose.body_from_mount.toRotationMatrix() *
                             camera.MountFromCamera().toRotationMatrix();
  return located;
}

RayHit IntersectGround(const CameraModel& camera, const CameraInEcef& located,
                       const Eigen::Vector2d& undistorted_pixel, const GroundModel& ground,
                       double max_range_m) {
  RayHit hit;
  const Eigen::Vector3d d = located.ecef_from_camera * camera.RayThroughPixel(undistorted_pixel);
  const Eigen::Vector3d& p = located.position;
  Eigen::Vector3d geodetic;
  const double h0 = HeightAboveGround(p, ground, &geodetic);
  if (h0 <= 0.0) {
    hit.status = RayHit::Status::kCameraBelowGround;
    return hit;
  }
  double t = 0.0;
  if (!InflatedEllipsoidHit(p, d, ground.HeightAt(geodetic.x(), geodetic.y()), &t)) {
    hit.status = RayHit::Status::kAboveHorizon;
    return hit;
  }
  if (t > 4.0 * max_range_m) {
    hit.status = RayHit::Status::kBeyondRange;
    hit.range_m = t;
    return hit;
  }
  // Secant iterations on f(t) = height above ground; the guess is within metres of the root.
  double t_prev = 0.0, f_prev = h0;
  double f = HeightAboveGround(p + t * d, ground, &geodetic);
  for (int i = 0; i < 30 && std::abs(f) > 1e-7; ++i) {
    const double slope = (f - f_prev) / (t - t_prev);
    if (slope == 0.0 || !std::isfinite(slope)) break;
    t_prev = t;
    f_prev = f;
    t -= f / slope;
    f = HeightAboveGround(p + t * d, ground, &geodetic);
  }
  hit.range_m = t;
  hit.geodetic = geodetic;
  if (!(t > 0.0) || std::abs(f) > 1e-3) {
    hit.status = RayHit::Status::kAboveHorizon;
  } else if (t > max_range_m) {
    hit.status = RayHit::Status::kBeyondRange;
  }
  return hit;
}

Eigen::Matrix3d FitHomography(const std::vector<Eigen::Vector2d>& from,
                              const std::vector<Eigen::Vector2d>& to) {
  const size_t n = from.size();
  // Hartley normalization of both point sets.
  auto normalizer = [](const std::vector<Eigen::Vector2d>& pts) {
    Eigen::Vector2d mean = Eigen::Vector2d::Zero();
    for (const auto& q : pts) mean += q;
    mean /= static_cast<double>(pts.size());
    double spread = 0.0;
    for (const auto& q : pts) spread += (q - mean).norm();
    spread /= static_cast<double>(pts.size());
    const double s = spread > 0 ? std::sqrt(2.0) / spread : 1.0;
    Eigen::Matrix3d t;
    t << s, 0, -s * mean.x(), 0, s, -s * mean.y(), 0, 0, 1;
    return t;
  };
  const Eigen::Matrix3d ta = normalizer(from), tb = normalizer(to);
  Eigen::MatrixXd a(2 * n, 9);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector2d p = ApplyHomography(ta, from[i]);
    const Eigen::Vector2d q = ApplyHomography(tb, to[i]);
    a.row(2 * i) << p.x(), p.y(), 1, 0, 0, 0, -q.x() * p.x(), -q.x() * p.y(), -q.x();
    a.row(2 * i + 1) << 0, 0, 0, p.x(), p.y(), 1, -q.y() * p.x(), -q.y() * p.y(), -q.y();
  }
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(a, Eigen::ComputeFullV);
  const Eigen::VectorXd h = svd.matrixV().col(8);
  Eigen::Matrix3d hn;
  hn << h(0), h(1), h(2), h(3), h(4), h(5), h(6), h(7), h(8);
  Eigen::Matrix3d result = tb.inverse() * hn * ta;
  return result / result(2, 2);
}

FrameGeometry ComputeFrameGeometry(const CameraModel& camera, const Pose& pose,
                                   const LocalFrame& frame, const MosaicGrid& grid,
                                   const GroundModel& ground, const GeometryOptions& options) {
  FrameGeometry result;
  const CameraInEcef located = LocateCamera(camera, pose);
  const double x_max = camera.width - 0.5, y_max = camera.height - 0.5;
  const int n = std::max(options.fit_grid, 2);
  std::vector<Eigen::Vector2d> image_pts, mosaic_pts;
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const Eigen::Vector2d px(-0.5 + (x_max + 0.5) * i / (n - 1),
                               -0.5 + (y_max + 0.5) * j / (n - 1));
      const RayHit hit = IntersectGround(camera, located, px, ground, options.max_range_m);
      if (!hit.ok()) {
        std::ostringstream problem;
        problem << "the ray through pixel (" << px.x() << ", " << px.y() << ") ";
        switch (hit.status) {
          case RayHit::Status::kAboveHorizon:
            problem << "points at or above the horizon";
            break;
          case RayHit::Status::kBeyondRange:
            problem << "meets the ground " << hit.range_m << " m away, beyond the limit of "
                    << options.max_range_m << " m";
            break;
          case RayHit::Status::kCameraBelowGround:
            problem << "starts below the ground";
            break;
          case RayHit::Status::kOk:
            break;
        }
        result.problem = problem.str();
        return result;
      }
      image_pts.push_back(px);
      mosaic_pts.push_back(
          grid.PixelFromPlane(frame.PlaneFromGeodetic(hit.geodetic.x(), hit.geodetic.y())));
    }
  }
  result.mosaic_from_image = FitHomography(image_pts, mosaic_pts);
  double sum_sq = 0.0;
  for (size_t k = 0; k < image_pts.size(); ++k) {
    const double e =
        (ApplyHomography(result.mosaic_from_image, image_pts[k]) - mosaic_pts[k]).norm();
    sum_sq += e * e;
    result.fit_max_px = std::max(result.fit_max_px, e);
  }
  result.fit_rms_px = std::sqrt(sum_sq / static_cast<double>(image_pts.size()));
  const std::array<int, 4> corner_index = {0, n - 1, n * n - 1, n * (n - 1)};
  for (int c = 0; c < 4; ++c) {
    result.footprint_m[c] = grid.PlaneFromPixel(mosaic_pts[corner_index[c]]);
  }
  result.ok = true;
  return result;
}

}  // namespace irmosaic
