#include "irmosaic/local_frame.h"

#include <ogr_spatialref.h>
#include <proj.h>

#include <GeographicLib/LocalCartesian.hpp>
#include <cmath>
#include <mutex>
#include <sstream>

#include "irmosaic/error.h"

namespace irmosaic {

struct LocalFrame::Impl {
  GeographicLib::LocalCartesian on_ellipsoid;
};

LocalFrame::LocalFrame(double origin_lat_deg, double origin_lon_deg)
    : lat0_(origin_lat_deg), lon0_(origin_lon_deg) {
  if (!std::isfinite(lat0_) || std::abs(lat0_) > 89.0 || !std::isfinite(lon0_)) {
    std::ostringstream problem;
    problem << "origin (" << lat0_ << ", " << lon0_ << ") is not a usable flight origin";
    throw InputError({"origin", 0, 0, ""}, problem.str(),
                     "give a finite latitude within 89 degrees of the equator");
  }
  impl_ = std::make_unique<Impl>(Impl{GeographicLib::LocalCartesian(lat0_, lon0_, 0.0)});
}

LocalFrame::~LocalFrame() = default;
LocalFrame::LocalFrame(const LocalFrame& other)
    : lat0_(other.lat0_), lon0_(other.lon0_), impl_(std::make_unique<Impl>(*other.impl_)) {}
LocalFrame& LocalFrame::operator=(const LocalFrame& other) {
  if (this != &other) {
    lat0_ = other.lat0_;
    lon0_ = other.lon0_;
    impl_ = std::make_unique<Impl>(*other.impl_);
  }
  return *this;
}

Eigen::Vector2d LocalFrame::PlaneFromGeodetic(double lat_deg, double lon_deg) const {
  double x = 0, y = 0, z = 0;
  impl_->on_ellipsoid.Forward(lat_deg, lon_deg, 0.0, x, y, z);
  return {x, y};
}

Eigen::Vector3d LocalFrame::EnuFromGeodetic(double lat_deg, double lon_deg, double height_m) const {
  double x = 0, y = 0, z = 0;
  impl_->on_ellipsoid.Forward(lat_deg, lon_deg, height_m, x, y, z);
  return {x, y, z};
}

Eigen::Vector3d LocalFrame::GeodeticFromEnu(const Eigen::Vector3d& enu) const {
  double lat = 0, lon = 0, h = 0;
  impl_->on_ellipsoid.Reverse(enu.x(), enu.y(), enu.z(), lat, lon, h);
  return {lat, lon, h};
}

std::string LocalFrame::CrsProj4() const {
  std::ostringstream text;
  text.precision(15);
  text << "+proj=ortho +lat_0=" << lat0_ << " +lon_0=" << lon0_
       << " +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs +type=crs";
  return text.str();
}

std::string LocalFrame::CrsWkt() const {
  OGRSpatialReference srs;
  srs.SetWellKnownGeogCS("WGS84");
  srs.SetOrthographic(lat0_, lon0_, 0.0, 0.0);
  srs.SetProjCS("irmosaic tangent plane (WGS 84 / orthographic)");
  char* wkt = nullptr;
  srs.exportToWkt(&wkt);
  std::string text = wkt ? wkt : "";
  CPLFree(wkt);
  return text;
}

struct PlaneToGeographic::Impl {
  PJ_CONTEXT* context = nullptr;
  PJ* transform = nullptr;
};

PlaneToGeographic::PlaneToGeographic(const LocalFrame& frame) : impl_(std::make_unique<Impl>()) {
  impl_->context = proj_context_create();
  const std::string source = frame.CrsProj4();
  impl_->transform = proj_create_crs_to_crs(impl_->context, source.c_str(), "EPSG:4326", nullptr);
  if (impl_->transform == nullptr) {
    proj_context_destroy(impl_->context);
    throw Error("PROJ cannot build the transform from " + source + " to EPSG:4326");
  }
  // Traditional GIS order: longitude, latitude on the geographic side.
  PJ* normalized = proj_normalize_for_visualization(impl_->context, impl_->transform);
  proj_destroy(impl_->transform);
  impl_->transform = normalized;
}

PlaneToGeographic::~PlaneToGeographic() {
  proj_destroy(impl_->transform);
  proj_context_destroy(impl_->context);
}

Eigen::Vector2d PlaneToGeographic::LatLonFromPlane(const Eigen::Vector2d& xy) const {
  const PJ_COORD out = proj_trans(impl_->transform, PJ_FWD, proj_coord(xy.x(), xy.y(), 0, 0));
  return {out.xy.y, out.xy.x};
}

Eigen::Vector2d PlaneToGeographic::PlaneFromLatLon(const Eigen::Vector2d& lat_lon) const {
  const PJ_COORD out =
      proj_trans(impl_->transform, PJ_INV, proj_coord(lat_lon.y(), lat_lon.x(), 0, 0));
  return {out.xy.x, out.xy.y};
}

}  // namespace irmosaic
