#include "irmosaic/camera.h"

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <set>

#include "irmosaic/error.h"
#include "irmosaic/pos.h"

namespace irmosaic {
namespace {

using nlohmann::json;

const std::set<std::string>& KnownFields() {
  static const std::set<std::string> fields = {
      "width", "height", "fx", "fy", "cx", "cy", "distortion", "boresight_deg", "lever_arm_m"};
  return fields;
}

double NumberField(const json& doc, const std::string& path, const std::string& name, bool required,
                   double fallback) {
  if (!doc.contains(name)) {
    if (required) {
      throw InputError({path, 0, 0, name}, "required field '" + name + "' is missing",
                       "add \"" + name + "\": <number> (docs/formats.md)");
    }
    return fallback;
  }
  const json& value = doc.at(name);
  if (!value.is_number()) {
    throw InputError({path, 0, 0, name}, "field '" + name + "' is not a number",
                     "write a plain JSON number");
  }
  return value.get<double>();
}

std::vector<double> ArrayField(const json& doc, const std::string& path, const std::string& name,
                               size_t min_size, size_t max_size) {
  if (!doc.contains(name)) return {};
  const json& value = doc.at(name);
  if (!value.is_array() || value.size() < min_size || value.size() > max_size) {
    throw InputError({path, 0, 0, name},
                     "field '" + name + "' must be an array of " + std::to_string(min_size) +
                         (min_size == max_size ? "" : " to " + std::to_string(max_size)) +
                         " numbers",
                     "see docs/formats.md");
  }
  std::vector<double> numbers;
  for (const json& item : value) {
    if (!item.is_number()) {
      throw InputError({path, 0, 0, name}, "field '" + name + "' holds a non-number",
                       "write plain JSON numbers");
    }
    numbers.push_back(item.get<double>());
  }
  return numbers;
}

}  // namespace

CameraModel CameraModel::LoadJson(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    throw InputError({path, 0, 0, ""}, "cannot open the camera file",
                     "check the path and that the file is readable");
  }
  json doc;
  try {
    doc = json::parse(in);
  } catch (const json::parse_error& e) {
    throw InputError({path, 0, 0, ""},
                     "not valid JSON (byte " + std::to_string(e.byte) + "): " + e.what(),
                     "fix the JSON syntax");
  } catch (const json::exception& e) {
    // E.g. out_of_range for a number beyond double ("555e555"), found by the fuzzer.
    throw InputError({path, 0, 0, ""}, std::string("not valid JSON: ") + e.what(),
                     "fix the JSON (numbers must fit a double)");
  }
  if (!doc.is_object()) {
    throw InputError({path, 0, 0, ""}, "the camera file is not a JSON object",
                     "write { \"width\": 640, ... } (docs/formats.md)");
  }
  for (const auto& item : doc.items()) {
    if (KnownFields().count(item.key()) == 0) {
      throw InputError({path, 0, 0, item.key()}, "unknown field '" + item.key() + "'",
                       "remove it or correct its spelling (docs/formats.md lists the fields)");
    }
  }
  CameraModel camera;
  const double width = NumberField(doc, path, "width", true, 0);
  const double height = NumberField(doc, path, "height", true, 0);
  for (const auto& [name, value] : {std::pair{"width", width}, std::pair{"height", height}}) {
    if (value != std::floor(value) || value < 1 || value > 100000) {
      throw InputError({path, 0, 0, name},
                       std::string("'") + name +
                           "' must be a whole number "
                           "of pixels from 1 to 100000",
                       "write the sensor size in pixels");
    }
  }
  camera.width = static_cast<int>(width);
  camera.height = static_cast<int>(height);
  camera.fx = NumberField(doc, path, "fx", true, 0);
  camera.fy = NumberField(doc, path, "fy", true, 0);
  camera.cx = NumberField(doc, path, "cx", false, (camera.width - 1) / 2.0);
  camera.cy = NumberField(doc, path, "cy", false, (camera.height - 1) / 2.0);
  camera.distortion = ArrayField(doc, path, "distortion", 0, 8);
  if (!camera.distortion.empty() && camera.distortion.size() != 4 &&
      camera.distortion.size() != 5 && camera.distortion.size() != 8) {
    throw InputError({path, 0, 0, "distortion"}, "OpenCV distortion has 0, 4, 5 or 8 coefficients",
                     "write [k1, k2, p1, p2] or [k1, k2, p1, p2, k3] or the 8-term form");
  }
  const std::vector<double> boresight = ArrayField(doc, path, "boresight_deg", 3, 3);
  if (!boresight.empty()) camera.boresight_deg = {boresight[0], boresight[1], boresight[2]};
  const std::vector<double> lever = ArrayField(doc, path, "lever_arm_m", 3, 3);
  if (!lever.empty()) camera.lever_arm_m = {lever[0], lever[1], lever[2]};
  camera.Validate(path);
  return camera;
}

void CameraModel::SaveJson(const std::string& path) const {
  json doc = {{"width", width},
              {"height", height},
              {"fx", fx},
              {"fy", fy},
              {"cx", cx},
              {"cy", cy},
              {"distortion", distortion},
              {"boresight_deg", {boresight_deg.x(), boresight_deg.y(), boresight_deg.z()}},
              {"lever_arm_m", {lever_arm_m.x(), lever_arm_m.y(), lever_arm_m.z()}}};
  std::ofstream out(path);
  out << doc.dump(2) << "\n";
  if (!out) throw OutputError("cannot write the camera file " + path);
}

void CameraModel::Validate(const std::string& source) const {
  auto fail = [&](const std::string& field, const std::string& problem, const std::string& fix) {
    throw InputError({source, 0, 0, field}, problem, fix);
  };
  if (width < 1 || height < 1) fail("width", "image size must be positive", "give the sensor size");
  for (const auto& [name, value] : {std::pair{"fx", fx}, std::pair{"fy", fy}}) {
    if (!std::isfinite(value) || value <= 0.0) {
      fail(name, std::string("focal length '") + name + "' must be a positive number of pixels",
           "give the focal length in pixels (focal length / pixel pitch)");
    }
  }
  if (!std::isfinite(cx) || cx < -0.5 || cx > width - 0.5) {
    fail("cx", "principal point x lies outside the image", "give cx in [-0.5, width - 0.5]");
  }
  if (!std::isfinite(cy) || cy < -0.5 || cy > height - 0.5) {
    fail("cy", "principal point y lies outside the image", "give cy in [-0.5, height - 0.5]");
  }
  for (double d : distortion) {
    if (!std::isfinite(d)) fail("distortion", "non-finite coefficient", "write finite numbers");
  }
  for (int i = 0; i < 3; ++i) {
    if (!std::isfinite(boresight_deg[i]) || std::abs(boresight_deg[i]) > 180.0) {
      fail("boresight_deg", "boresight angles must be finite degrees in [-180, 180]",
           "give roll, pitch, yaw of the camera on its mount");
    }
    if (!std::isfinite(lever_arm_m[i]) || std::abs(lever_arm_m[i]) > 100.0) {
      fail("lever_arm_m", "lever arm must be finite metres within 100 m",
           "give x, y, z in aircraft body axes");
    }
  }
}

bool CameraModel::HasDistortion() const {
  for (double d : distortion) {
    if (d != 0.0) return true;
  }
  return false;
}

Eigen::Vector2d CameraModel::Undistort(const Eigen::Vector2d& pixel) const {
  if (!HasDistortion()) return pixel;
  const cv::Matx33d k(fx, 0, cx, 0, fy, cy, 0, 0, 1);
  std::vector<cv::Point2d> in{{pixel.x(), pixel.y()}}, out;
  cv::undistortPoints(in, out, k, distortion, cv::noArray(), k,
                      cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 50, 1e-12));
  return {out[0].x, out[0].y};
}

Eigen::Vector2d CameraModel::Distort(const Eigen::Vector2d& pixel) const {
  if (!HasDistortion()) return pixel;
  std::vector<cv::Point3d> in{{(pixel.x() - cx) / fx, (pixel.y() - cy) / fy, 1.0}};
  std::vector<cv::Point2d> out;
  const cv::Matx33d k(fx, 0, cx, 0, fy, cy, 0, 0, 1);
  cv::projectPoints(in, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), k, distortion, out);
  return {out[0].x, out[0].y};
}

Eigen::Vector3d CameraModel::RayThroughPixel(const Eigen::Vector2d& p) const {
  return Eigen::Vector3d((p.x() - cx) / fx, (p.y() - cy) / fy, 1.0).normalized();
}

Eigen::Quaterniond CameraModel::MountFromCamera() const {
  // Columns: camera x (image right) = mount +y, camera y (image down) = mount -x,
  // camera z (optical axis) = mount +z (down when the mount is level).
  Eigen::Matrix3d nominal;
  nominal << 0, -1, 0, 1, 0, 0, 0, 0, 1;
  const Eigen::Quaterniond boresight =
      RotationFromYpr(boresight_deg.z(), boresight_deg.y(), boresight_deg.x());
  return Eigen::Quaterniond(nominal) * boresight;
}

CameraModel DefaultInfraredCamera(double fx_px) {
  CameraModel camera;
  camera.width = 640;
  camera.height = 512;
  camera.fx = camera.fy = fx_px;
  camera.cx = (camera.width - 1) / 2.0;
  camera.cy = (camera.height - 1) / 2.0;
  return camera;
}

}  // namespace irmosaic
