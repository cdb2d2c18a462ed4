#pragma once

#include <Eigen/Core>
#include <memory>
#include <string>

#include "irmosaic/export.h"

namespace irmosaic {

// The mosaic plane: the tangent plane of the WGS84 ellipsoid at the flight origin.
//
// Plane coordinates (x east, y north, metres) of a ground point are those of its footprint on
// the ellipsoid, projected orthogonally onto the tangent plane; this is exactly the
// ellipsoidal orthographic projection (EPSG method 9840, PROJ `+proj=ortho`) centred at the
// origin, so every GIS tool reads the mosaic through CrsWkt(). GeographicLib does the geodesy.
class IRMOSAIC_EXPORT LocalFrame {
 public:
  LocalFrame(double origin_lat_deg, double origin_lon_deg);
  ~LocalFrame();
  LocalFrame(const LocalFrame& other);
  LocalFrame& operator=(const LocalFrame& other);

  double origin_lat_deg() const { return lat0_; }
  double origin_lon_deg() const { return lon0_; }

  // Plane coordinates (m) of a point given by latitude and longitude (height is irrelevant).
  Eigen::Vector2d PlaneFromGeodetic(double lat_deg, double lon_deg) const;
  // East-north-up (m) of a 3-D point, origin on the ellipsoid at the flight origin.
  Eigen::Vector3d EnuFromGeodetic(double lat_deg, double lon_deg, double height_m) const;
  // Geodetic position of an ENU point.
  Eigen::Vector3d GeodeticFromEnu(const Eigen::Vector3d& enu) const;  // (lat, lon, height)

  // The plane's CRS as WKT (OGC WKT 1, which GeoTIFF and every GDAL reader accept).
  std::string CrsWkt() const;
  // Same CRS as a PROJ string.
  std::string CrsProj4() const;

 private:
  double lat0_;
  double lon0_;
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Transforms plane coordinates to longitude/latitude through PROJ (independent of
// GeographicLib, so each checks the other). Not thread-safe: one per thread.
class IRMOSAIC_EXPORT PlaneToGeographic {
 public:
  explicit PlaneToGeographic(const LocalFrame& frame);
  ~PlaneToGeographic();
  PlaneToGeographic(const PlaneToGeographic&) = delete;
  PlaneToGeographic& operator=(const PlaneToGeographic&) = delete;

  // (lat_deg, lon_deg) of plane point (x, y) metres.
  Eigen::Vector2d LatLonFromPlane(const Eigen::Vector2d& xy) const;
  // Plane point of (lat_deg, lon_deg).
  Eigen::Vector2d PlaneFromLatLon(const Eigen::Vector2d& lat_lon) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Pixel grid on the mosaic plane at a ground sample distance. Mosaic pixel (col, row) has its
// centre at plane (col * gsd, -row * gsd): pixel (0, 0) is centred on the origin, rows grow
// southward, indices are signed so the mosaic grows in every direction.
struct IRMOSAIC_EXPORT MosaicGrid {
  double gsd_m = 0.5;

  Eigen::Vector2d PixelFromPlane(const Eigen::Vector2d& xy) const {
    return {xy.x() / gsd_m, -xy.y() / gsd_m};
  }
  Eigen::Vector2d PlaneFromPixel(const Eigen::Vector2d& px) const {
    return {px.x() * gsd_m, -px.y() * gsd_m};
  }
  // GDAL geotransform of a raster whose pixel (0, 0) is mosaic pixel (col0, row0).
  void GeoTransform(double col0, double row0, double gt[6]) const {
    gt[0] = (col0 - 0.5) * gsd_m;
    gt[1] = gsd_m;
    gt[2] = 0.0;
    gt[3] = -(row0 - 0.5) * gsd_m;
    gt[4] = 0.0;
    gt[5] = -gsd_m;
  }
};

}  // namespace irmosaic
