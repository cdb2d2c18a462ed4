// Geometry of the foundation: POS + camera -> correction homography on the mosaic plane.
#include <gtest/gtest.h>

#include <GeographicLib/Geocentric.hpp>
#include <GeographicLib/Geodesic.hpp>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "irmosaic/frame_geometry.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/orthorectify.h"

namespace irmosaic {
namespace {

constexpr double kLat0 = 47.2, kLon0 = 8.5;  // Flight origin.

// Metres between two (lat, lon) points on the ellipsoid.
double GeodesicDistance(double lat1, double lon1, double lat2, double lon2) {
  double s12 = 0;
  GeographicLib::Geodesic::WGS84().Inverse(lat1, lon1, lat2, lon2, s12);
  return s12;
}

// Reference: walk the pixel's ray by bisection on geodetic height (GeographicLib only),
// independent of IntersectGround's secant solver and of any homography.
Eigen::Vector2d ReferenceGroundLatLon(const CameraModel& camera, const Pose& pose,
                                      const Eigen::Vector2d& pixel, double ground_h) {
  const CameraInEcef located = LocateCamera(camera, pose);
  const Eigen::Vector3d d = located.ecef_from_camera * camera.RayThroughPixel(pixel);
  const auto& earth = GeographicLib::Geocentric::WGS84();
  auto height = [&](double t, double* lat, double* lon) {
    const Eigen::Vector3d p = located.position + t * d;
    double h = 0;
    earth.Reverse(p.x(), p.y(), p.z(), *lat, *lon, h);
    return h - ground_h;
  };
  double lo = 0.0, hi = 200000.0, lat = 0, lon = 0;
  for (int i = 0; i < 200; ++i) {
    const double mid = 0.5 * (lo + hi);
    (height(mid, &lat, &lon) > 0 ? lo : hi) = mid;
  }
  height(0.5 * (lo + hi), &lat, &lon);
  return {lat, lon};
}

// A pose `east_m`, `north_m` from the origin at `height_m`, looking `off_nadir_deg` sideways
// through the sweep gimbal, with the aircraft heading `yaw_deg`.
Pose MakePose(const LocalFrame& frame, double east_m, double north_m, double height_m,
              double yaw_deg, double off_nadir_deg, double tilt_deg = 0.0) {
  const Eigen::Vector3d geo = frame.GeodeticFromEnu({east_m, north_m, 0.0});
  PosRecord record;
  record.lat_deg = geo.x();
  record.lon_deg = geo.y();
  record.height_m = height_m;
  record.yaw_deg = yaw_deg;
  record.roll_deg = 2.0;
  record.pitch_deg = -1.5;
  record.gimbal_roll_deg = off_nadir_deg;
  record.gimbal_pitch_deg = tilt_deg;
  return PoseFromRecord(record);
}

TEST(GeometryTest, HomographyThroughCrsMatchesDirectRayWithin5cm) {
  const LocalFrame frame(kLat0, kLon0);
  const MosaicGrid grid{0.3};
  const FlatGround ground(420.0);
  // The project's default long-focal-length infrared camera (640x512, fx 2400 px: 15 deg
  // field of view). A homography cannot follow the Earth's curvature across a wider footprint
  // at 60 degrees off nadir to 5 cm; FrameGeometry::fit_max_px reports that figure per frame.
  const CameraModel camera = DefaultInfraredCamera();
  PlaneToGeographic to_geographic(frame);
  double worst_m = 0.0;
  // Off-nadir sweep angles; the aircraft adds 2 deg of roll, so the last case is 60 deg.
  for (double off_nadir : {0.0, 30.0, 45.0, 58.0}) {
    for (const auto& [east, north] : {std::pair{0.0, 0.0}, std::pair{7071.0, 7071.0},
                                      std::pair{-10000.0, 0.0}, std::pair{0.0, -10000.0}}) {
      for (double yaw : {0.0, 137.0}) {
        const Pose pose = MakePose(frame, east, north, 420.0 + 800.0, yaw, off_nadir, 0.0);
        const FrameGeometry geometry = ComputeFrameGeometry(camera, pose, frame, grid, ground);
        ASSERT_TRUE(geometry.ok) << geometry.problem;
        for (const Eigen::Vector2d& px :
             {Eigen::Vector2d(0, 0), Eigen::Vector2d(639, 0), Eigen::Vector2d(319.5, 255.5),
              Eigen::Vector2d(17, 499), Eigen::Vector2d(639, 511), Eigen::Vector2d(401, 77)}) {
          const Eigen::Vector2d mosaic = ApplyHomography(geometry.mosaic_from_image, px);
          const Eigen::Vector2d ll = to_geographic.LatLonFromPlane(grid.PlaneFromPixel(mosaic));
          const Eigen::Vector2d ref = ReferenceGroundLatLon(camera, pose, px, 420.0);
          worst_m = std::max(worst_m, GeodesicDistance(ll.x(), ll.y(), ref.x(), ref.y()));
        }
      }
    }
  }
  RecordProperty("worst_m", std::to_string(worst_m));
  EXPECT_LT(worst_m, 0.05) << "worst ground error " << worst_m << " m";
}

TEST(GeometryTest, LatLonPlaneRoundTripBelow1mm) {
  const LocalFrame frame(kLat0, kLon0);
  PlaneToGeographic proj(frame);
  double worst_m = 0.0;
  for (double dlat = -0.1; dlat <= 0.1; dlat += 0.05) {
    for (double dlon = -0.15; dlon <= 0.15; dlon += 0.05) {
      const double lat = kLat0 + dlat, lon = kLon0 + dlon;
      // GeographicLib forward, PROJ inverse: the two libraries must agree on the CRS.
      const Eigen::Vector2d xy = frame.PlaneFromGeodetic(lat, lon);
      const Eigen::Vector2d back = proj.LatLonFromPlane(xy);
      worst_m = std::max(worst_m, GeodesicDistance(lat, lon, back.x(), back.y()));
      // And PROJ both ways.
      const Eigen::Vector2d xy2 = proj.PlaneFromLatLon({lat, lon});
      worst_m = std::max(worst_m, (xy2 - xy).norm());
    }
  }
  EXPECT_LT(worst_m, 0.001) << "worst " << worst_m << " m";
}

TEST(GeometryTest, NadirFootprintMatchesPinholeWithin0p1Percent) {
  const LocalFrame frame(kLat0, kLon0);
  const MosaicGrid grid{0.5};
  const FlatGround ground(100.0);
  const CameraModel camera = DefaultInfraredCamera(1200.0);
  PosRecord record;
  record.lat_deg = kLat0;
  record.lon_deg = kLon0;
  record.height_m = 100.0 + 1000.0;
  const FrameGeometry geometry =
      ComputeFrameGeometry(camera, PoseFromRecord(record), frame, grid, ground);
  ASSERT_TRUE(geometry.ok) << geometry.problem;
  const double width_m = (geometry.footprint_m[1] - geometry.footprint_m[0]).norm();
  const double height_m = (geometry.footprint_m[3] - geometry.footprint_m[0]).norm();
  const double expected_w = 1000.0 * camera.width / camera.fx;
  const double expected_h = 1000.0 * camera.height / camera.fy;
  EXPECT_NEAR(width_m / expected_w, 1.0, 1e-3);
  EXPECT_NEAR(height_m / expected_h, 1.0, 1e-3);
}

TEST(GeometryTest, ConventionsHeadingAndSweepDirection) {
  const LocalFrame frame(kLat0, kLon0);
  const MosaicGrid grid{1.0};
  const FlatGround ground(0.0);
  const CameraModel camera = DefaultInfraredCamera(1500.0);
  auto centre_of = [&](double yaw, double sweep, double tilt) {
    PosRecord r;
    r.lat_deg = kLat0;
    r.lon_deg = kLon0;
    r.height_m = 1000.0;
    r.yaw_deg = yaw;
    r.gimbal_roll_deg = sweep;
    r.gimbal_pitch_deg = tilt;
    const FrameGeometry g = ComputeFrameGeometry(camera, PoseFromRecord(r), frame, grid, ground);
    EXPECT_TRUE(g.ok);
    return std::pair{grid.PlaneFromPixel(ApplyHomography(g.mosaic_from_image, {319.5, 255.5})),
                     grid.PlaneFromPixel(ApplyHomography(g.mosaic_from_image, {319.5, 0.0}))};
  };
  // Heading north, nadir: the image top points north (y grows).
  auto [c0, top0] = centre_of(0, 0, 0);
  EXPECT_NEAR(c0.norm(), 0.0, 0.01);
  EXPECT_GT(top0.y(), 100.0);
  // Heading east (yaw 90): the image top points east.
  auto [c1, top1] = centre_of(90, 0, 0);
  EXPECT_GT(top1.x(), 100.0);
  // Positive sweep (gimbal roll, right-handed about the nose) looks to port, as a positive
  // aircraft roll does: heading north, port is west.
  auto [c2, top2] = centre_of(0, 45, 0);
  EXPECT_NEAR(c2.x(), -1000.0, 1.0);  // tan(45 deg) * 1000 m, to port (west).
  EXPECT_NEAR(c2.y(), 0.0, 1.0);
  // Positive gimbal pitch tilts the view forward (nose-up rotation of the mount).
  auto [c3, top3] = centre_of(0, 0, 30);
  EXPECT_NEAR(c3.y(), 1000.0 * std::tan(30.0 * M_PI / 180.0), 1.0);
}

TEST(GeometryTest, RayAboveHorizonIsReportedNotWrapped) {
  const LocalFrame frame(kLat0, kLon0);
  PosRecord r;
  r.lat_deg = kLat0;
  r.lon_deg = kLon0;
  r.height_m = 1000.0;
  r.gimbal_roll_deg = 85.0;  // Top of the sweep: upper image rows see the sky.
  const FrameGeometry g = ComputeFrameGeometry(DefaultInfraredCamera(1500.0), PoseFromRecord(r),
                                               frame, MosaicGrid{1.0}, FlatGround(0.0));
  EXPECT_FALSE(g.ok);
  EXPECT_NE(g.problem.find("horizon"), std::string::npos) << g.problem;
}

TEST(GeometryTest, AbsurdRangeIsRefusedByConfigurableLimit) {
  const LocalFrame frame(kLat0, kLon0);
  PosRecord r;
  r.lat_deg = kLat0;
  r.lon_deg = kLon0;
  r.height_m = 1000.0;
  r.gimbal_roll_deg = 80.0;  // Grazing: ground ~5.8 km away at the centre.
  GeometryOptions options;
  options.max_range_m = 3000.0;
  const FrameGeometry g = ComputeFrameGeometry(DefaultInfraredCamera(3000.0), PoseFromRecord(r),
                                               frame, MosaicGrid{1.0}, FlatGround(0.0), options);
  EXPECT_FALSE(g.ok);
  EXPECT_NE(g.problem.find("beyond the limit"), std::string::npos) << g.problem;
}

// Ground beyond max_range_m is clipped off, not the whole frame refused: the kept part is the
// convex polygon of pixels whose rays meet the ground within the range, the homography is exact
// on it, and the orthoimage paints only it.
TEST(GeometryTest, FarGroundIsClippedAtTheRangeLimitWithAWarning) {
  const LocalFrame frame(kLat0, kLon0);
  PosRecord r;
  r.lat_deg = kLat0;
  r.lon_deg = kLon0;
  r.height_m = 1000.0;
  r.gimbal_roll_deg = 60.0;  // Ground 1.70 km to 2.47 km away across the image.
  const CameraModel camera = DefaultInfraredCamera(3000.0);
  const Pose pose = PoseFromRecord(r);
  GeometryOptions options;
  options.max_range_m = 2000.0;
  const MosaicGrid grid{1.0};
  const FrameGeometry g = ComputeFrameGeometry(camera, pose, frame, grid, FlatGround(0.0), options);
  ASSERT_TRUE(g.ok) << g.problem;
  EXPECT_NE(g.warning.find("clipped"), std::string::npos) << g.warning;
  EXPECT_NE(g.warning.find("2000 m"), std::string::npos) << g.warning;
  ASSERT_GE(g.image_clip.size(), 3u);
  EXPECT_GT(g.kept_fraction, 0.3);
  EXPECT_LT(g.kept_fraction, 0.7);
  std::printf("clipped at %.0f m: %.1f%% kept, %zu vertices, fit rms %.4f px max %.4f px\n",
              options.max_range_m, 100 * g.kept_fraction, g.image_clip.size(), g.fit_rms_px,
              g.fit_max_px);
  std::vector<cv::Point2f> contour;
  for (const Eigen::Vector2d& p : g.image_clip) contour.emplace_back(p.x(), p.y());
  const CameraInEcef located = LocateCamera(camera, pose);
  int inside = 0, outside = 0;
  double worst_px = 0.0;
  for (int j = 0; j <= 16; ++j) {
    for (int i = 0; i <= 20; ++i) {
      const Eigen::Vector2d px(-0.5 + 640.0 * i / 20, -0.5 + 512.0 * j / 16);
      const double margin = cv::pointPolygonTest(
          contour, cv::Point2f(static_cast<float>(px.x()), static_cast<float>(px.y())), true);
      const RayHit hit = IntersectGround(camera, located, px, FlatGround(0.0), 1e6);
      ASSERT_TRUE(hit.ok());
      if (margin > 2.0) {  // Kept: within the range, and placed exactly by the homography.
        ++inside;
        EXPECT_LE(hit.range_m, options.max_range_m) << px.transpose();
        const Eigen::Vector2d exact =
            grid.PixelFromPlane(frame.PlaneFromGeodetic(hit.geodetic.x(), hit.geodetic.y()));
        worst_px = std::max(worst_px, (ApplyHomography(g.mosaic_from_image, px) - exact).norm());
      } else if (margin < -2.0) {  // Clipped: beyond the range.
        ++outside;
        EXPECT_GT(hit.range_m, options.max_range_m) << px.transpose();
      }
    }
  }
  EXPECT_GT(inside, 50);
  EXPECT_GT(outside, 50);
  EXPECT_LT(worst_px, 0.05);  // Mosaic pixels of 1 m.
  // The footprint lies in the kept part: its corners are within the range.
  // (The camera is above the plane's origin: horizontal distance is the plane radius.)
  for (const Eigen::Vector2d& corner_m : g.footprint_m) {
    EXPECT_LT(corner_m.norm(), std::sqrt(2000.0 * 2000.0 - 1000.0 * 1000.0) + 2.0);
  }
  // The orthoimage paints only the kept part.
  cv::Mat image(512, 640, CV_16U, cv::Scalar(1000));
  const OrthoImage whole = Orthorectify(image, camera, g.mosaic_from_image);
  const OrthoImage kept = Orthorectify(image, camera, g.mosaic_from_image, {}, g.image_clip);
  const double kept_area = cv::countNonZero(kept.mask), whole_area = cv::countNonZero(whole.mask);
  EXPECT_LT(kept_area, 0.8 * whole_area);
  EXPECT_GT(kept_area, 0.2 * whole_area);
  const Eigen::Matrix3d image_from_ortho = kept.ortho_from_image.inverse();
  for (int y = 0; y < kept.mask.rows; y += 7) {
    for (int x = 0; x < kept.mask.cols; x += 7) {
      if (!kept.mask.at<uint8_t>(y, x)) continue;
      const Eigen::Vector2d px = ApplyHomography(image_from_ortho, Eigen::Vector2d(x, y));
      EXPECT_GT(
          cv::pointPolygonTest(
              contour, cv::Point2f(static_cast<float>(px.x()), static_cast<float>(px.y())), true),
          -1.5)
          << px.transpose();
    }
  }
}

TEST(GeometryTest, CrsWktIsOrthographicOnWgs84) {
  const LocalFrame frame(kLat0, kLon0);
  const std::string wkt = frame.CrsWkt();
  EXPECT_NE(wkt.find("Orthographic"), std::string::npos) << wkt;
  EXPECT_NE(wkt.find("WGS"), std::string::npos) << wkt;
  EXPECT_NE(wkt.find("47.2"), std::string::npos) << wkt;
}

}  // namespace
}  // namespace irmosaic
