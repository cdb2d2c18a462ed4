#include "irmosaic/frame_geometry.h"

#include <Eigen/Cholesky>
#include <Eigen/SVD>
#include <GeographicLib/Geocentric.hpp>
#include <cmath>
#include <opencv2/imgproc.hpp>
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

namespace {

std::string RayProblem(const Eigen::Vector2d& px, const RayHit& hit, double max_range_m) {
  std::ostringstream problem;
  problem << "the ray through pixel (" << px.x() << ", " << px.y() << ") ";
  switch (hit.status) {
    case RayHit::Status::kAboveHorizon:
      problem << "points at or above the horizon";
      break;
    case RayHit::Status::kBeyondRange:
      problem << "meets the ground " << hit.range_m << " m away, beyond the limit of "
              << max_range_m << " m";
      break;
    case RayHit::Status::kCameraBelowGround:
      problem << "starts below the ground";
      break;
    case RayHit::Status::kOk:
      break;
  }
  return problem.str();
}

// The part of the image whose rays meet the ground within the range limit. It is convex (the
// rays within a range of a camera above flat ground form a cone about the vertical), so it is
// the convex hull of in-range samples of a fine grid plus the boundary points found by
// bisection between neighbouring in- and out-of-range samples (to 1/64 of the grid step).
std::vector<Eigen::Vector2d> InRangeRegion(const CameraModel& camera, const CameraInEcef& located,
                                           const GroundModel& ground, double max_range_m) {
  constexpr int kCols = 33;
  const int rows = std::max(3, kCols * camera.height / std::max(camera.width, 1));
  const double x_max = camera.width - 0.5, y_max = camera.height - 0.5;
  auto at = [&](int i, int j) {
    return Eigen::Vector2d(-0.5 + (x_max + 0.5) * i / (kCols - 1),
                           -0.5 + (y_max + 0.5) * j / (rows - 1));
  };
  auto in_range = [&](const Eigen::Vector2d& px) {
    return IntersectGround(camera, located, px, ground, max_range_m).ok();
  };
  std::vector<char> inside(static_cast<size_t>(kCols) * rows);
  for (int j = 0; j < rows; ++j)
    for (int i = 0; i < kCols; ++i) inside[j * kCols + i] = in_range(at(i, j));
  std::vector<cv::Point2f> points;
  auto add = [&](const Eigen::Vector2d& p) {
    points.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()));
  };
  auto bisect = [&](Eigen::Vector2d good, Eigen::Vector2d bad) {
    for (int k = 0; k < 6; ++k) {
      const Eigen::Vector2d mid = 0.5 * (good + bad);
      (in_range(mid) ? good : bad) = mid;
    }
    add(good);
  };
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < kCols; ++i) {
      if (!inside[j * kCols + i]) continue;
      add(at(i, j));
      const int neighbours[4][2] = {{i + 1, j}, {i - 1, j}, {i, j + 1}, {i, j - 1}};
      for (const auto& n : neighbours) {
        if (n[0] < 0 || n[0] >= kCols || n[1] < 0 || n[1] >= rows) continue;
        if (!inside[n[1] * kCols + n[0]]) bisect(at(i, j), at(n[0], n[1]));
      }
    }
  }
  std::vector<Eigen::Vector2d> polygon;
  if (points.size() < 3) return polygon;
  std::vector<cv::Point2f> hull;
  cv::convexHull(points, hull);
  for (const cv::Point2f& p : hull) polygon.emplace_back(p.x, p.y);
  return polygon;
}

double PolygonArea(const std::vector<Eigen::Vector2d>& polygon) {
  double twice = 0.0;
  for (size_t k = 0; k < polygon.size(); ++k) {
    const Eigen::Vector2d& a = polygon[k];
    const Eigen::Vector2d& b = polygon[(k + 1) % polygon.size()];
    twice += a.x() * b.y() - a.y() * b.x();
  }
  return std::abs(twice) / 2.0;
}

}  // namespace

FrameGeometry ComputeFrameGeometry(const CameraModel& camera, const Pose& pose,
                                   const LocalFrame& frame, const MosaicGrid& grid,
                                   const GroundModel& ground, const GeometryOptions& options) {
  FrameGeometry result;
  const CameraInEcef located = LocateCamera(camera, pose);
  const double x_max = camera.width - 0.5, y_max = camera.height - 0.5;
  const int n = std::max(options.fit_grid, 2);
  // The fit samples an n x n grid over the frame, or over the kept part of a clipped frame.
  Eigen::Vector2d lo(-0.5, -0.5), hi(x_max, y_max);
  std::vector<cv::Point2f> clip_contour;
  for (int attempt = 0; attempt < 2; ++attempt) {
    std::vector<Eigen::Vector2d> image_pts, mosaic_pts;
    std::string beyond;  // First ray beyond the range limit.
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i < n; ++i) {
        const Eigen::Vector2d px(lo.x() + (hi.x() - lo.x()) * i / (n - 1),
                                 lo.y() + (hi.y() - lo.y()) * j / (n - 1));
        if (!clip_contour.empty() &&
            cv::pointPolygonTest(
                clip_contour, cv::Point2f(static_cast<float>(px.x()), static_cast<float>(px.y())),
                false) < 0) {
          continue;
        }
        const RayHit hit = IntersectGround(camera, located, px, ground, options.max_range_m);
        if (hit.status == RayHit::Status::kBeyondRange) {
          if (beyond.empty()) beyond = RayProblem(px, hit, options.max_range_m);
          continue;
        }
        if (!hit.ok()) {
          // Above the horizon or below the ground: the pose is wrong, nothing to clip.
          result.problem = RayProblem(px, hit, options.max_range_m);
          return result;
        }
        image_pts.push_back(px);
        mosaic_pts.push_back(
            grid.PixelFromPlane(frame.PlaneFromGeodetic(hit.geodetic.x(), hit.geodetic.y())));
      }
    }
    if (attempt == 0 && !beyond.empty()) {
      // Ground beyond the limit: keep the part of the frame within it, and fit over that part.
      result.image_clip = InRangeRegion(camera, located, ground, options.max_range_m);
      const double frame_area = (x_max + 0.5) * (y_max + 0.5);
      result.kept_fraction =
          result.image_clip.size() >= 3 ? PolygonArea(result.image_clip) / frame_area : 0.0;
      if (result.kept_fraction < 0.01) {
        result.problem = beyond + "; less than 1% of the frame sees ground within it";
        result.image_clip.clear();
        return result;
      }
      lo = hi = result.image_clip.front();
      for (const Eigen::Vector2d& p : result.image_clip) {
        clip_contour.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()));
        lo = lo.cwiseMin(p);
        hi = hi.cwiseMax(p);
      }
      std::ostringstream warning;
      warning << "ground beyond the range limit of " << options.max_range_m
              << " m clipped off the frame (" << beyond << "); "
              << std::lround(100.0 * result.kept_fraction) << "% of the frame kept";
      result.warning = warning.str();
      continue;
    }
    // The kept polygon's vertices are in range by construction and make the fit span it.
    for (const Eigen::Vector2d& px : result.image_clip) {
      const RayHit hit = IntersectGround(camera, located, px, ground, options.max_range_m);
      if (!hit.ok()) continue;
      image_pts.push_back(px);
      mosaic_pts.push_back(
          grid.PixelFromPlane(frame.PlaneFromGeodetic(hit.geodetic.x(), hit.geodetic.y())));
    }
    if (image_pts.size() < 8) {
      result.problem = beyond.empty() ? "too few rays meet the ground"
                                      : beyond + "; too little of the frame sees ground within it";
      return result;
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
    // Footprint: the frame's corners, or for a clipped frame the kept polygon's vertices
    // nearest to them.
    const std::array<Eigen::Vector2d, 4> corners = {
        Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(x_max, -0.5), Eigen::Vector2d(x_max, y_max),
        Eigen::Vector2d(-0.5, y_max)};
    const std::array<int, 4> corner_index = {0, n - 1, n * n - 1, n * (n - 1)};
    for (int c = 0; c < 4; ++c) {
      if (result.image_clip.empty()) {  // The exact rays of the grid's corners.
        result.footprint_m[c] = grid.PlaneFromPixel(mosaic_pts[corner_index[c]]);
        continue;
      }
      Eigen::Vector2d corner = corners[c];
      {
        double best = INFINITY;
        for (const Eigen::Vector2d& p : result.image_clip) {
          if ((p - corners[c]).norm() < best) {
            best = (p - corners[c]).norm();
            corner = p;
          }
        }
      }
      result.footprint_m[c] =
          grid.PlaneFromPixel(ApplyHomography(result.mosaic_from_image, corner));
    }
    result.ok = true;
    return result;
  }
  return result;
}

Eigen::Matrix<double, 10, 10> PosPriorSqrtInformation(
    const CameraModel& camera, const Pose& pose, const LocalFrame& frame, const MosaicGrid& grid,
    const GroundModel& ground, double position_sigma_m, double attitude_sigma_deg,
    double model_sigma_px) {
  GeometryOptions options;
  options.fit_grid = 3;  // The five points only need the ray grid's corners and centre.
  const std::array<Eigen::Vector2d, 5> points = {
      Eigen::Vector2d(0, 0), Eigen::Vector2d(camera.width - 1, 0),
      Eigen::Vector2d(camera.width - 1, camera.height - 1), Eigen::Vector2d(0, camera.height - 1),
      Eigen::Vector2d((camera.width - 1) / 2.0, (camera.height - 1) / 2.0)};
  auto place = [&](const Pose& p, Eigen::Matrix<double, 10, 1>* out) {
    const FrameGeometry g = ComputeFrameGeometry(camera, p, frame, grid, ground, options);
    if (!g.ok) return false;
    for (int k = 0; k < 5; ++k)
      out->segment<2>(2 * k) = ApplyHomography(g.mosaic_from_image, points[k]);
    return true;
  };
  Eigen::Matrix<double, 10, 6> jacobian = Eigen::Matrix<double, 10, 6>::Zero();
  const double step_m = 0.5, step_deg = 0.05;
  for (int axis = 0; axis < 6; ++axis) {
    Eigen::Matrix<double, 10, 1> plus, minus;
    Pose a = pose, b = pose;
    const double step = axis < 3 ? step_m : step_deg;
    if (axis < 3) {
      Eigen::Vector3d delta = Eigen::Vector3d::Zero();
      delta[axis] = step;
      // Move in the local ENU frame of the pose itself.
      const LocalFrame here(pose.lat_deg, pose.lon_deg);
      const Eigen::Vector3d enu = here.EnuFromGeodetic(pose.lat_deg, pose.lon_deg, pose.height_m);
      const Eigen::Vector3d ga = here.GeodeticFromEnu(enu + delta);
      const Eigen::Vector3d gb = here.GeodeticFromEnu(enu - delta);
      a.lat_deg = ga.x(), a.lon_deg = ga.y(), a.height_m = ga.z();
      b.lat_deg = gb.x(), b.lon_deg = gb.y(), b.height_m = gb.z();
    } else {
      // Small rotations of the body about its own x (roll), y (pitch), z (yaw) axes.
      const double rad = step * M_PI / 180.0;
      const Eigen::Vector3d axis_vec =
          axis == 3 ? Eigen::Vector3d::UnitX()
                    : (axis == 4 ? Eigen::Vector3d::UnitY() : Eigen::Vector3d::UnitZ());
      a.ned_from_body = pose.ned_from_body * Eigen::AngleAxisd(rad, axis_vec);
      b.ned_from_body = pose.ned_from_body * Eigen::AngleAxisd(-rad, axis_vec);
    }
    if (!place(a, &plus) || !place(b, &minus)) continue;
    jacobian.col(axis) = (plus - minus) / (2.0 * step);
  }
  Eigen::Matrix<double, 6, 1> variances;
  variances << Eigen::Vector3d::Constant(position_sigma_m * position_sigma_m),
      Eigen::Vector3d::Constant(attitude_sigma_deg * attitude_sigma_deg);
  Eigen::Matrix<double, 10, 10> covariance =
      jacobian * variances.asDiagonal() * jacobian.transpose();
  covariance.diagonal().array() += model_sigma_px * model_sigma_px;
  // L with L^T L = covariance^-1: the inverse of the Cholesky factor.
  const Eigen::LLT<Eigen::Matrix<double, 10, 10>> llt(covariance);
  const Eigen::Matrix<double, 10, 10> lower = llt.matrixL();
  return lower.triangularView<Eigen::Lower>().solve(Eigen::Matrix<double, 10, 10>::Identity());
}

}  // namespace irmosaic
