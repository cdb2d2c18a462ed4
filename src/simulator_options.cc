// SynthOptions: validity check and the JSON form read by `irmosaic synth --config`.
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <sstream>

#include "irmosaic/error.h"
#include "irmosaic/simulator.h"

namespace irmosaic {
namespace {

using nlohmann::json;

// A JSON key bound to a member: how to read it and how to write it.
struct Binding {
  std::string key;
  std::function<void(const json&)> read;
  std::function<json()> write;
};

template <typename T>
Binding Bind(const std::string& key, T* member) {
  return {key, [member](const json& v) { *member = v.get<T>(); },
          [member]() { return json(*member); }};
}

Binding BindVector3(const std::string& key, Eigen::Vector3d* member) {
  return {key,
          [member](const json& v) {
            if (!v.is_array() || v.size() != 3)
              throw json::type_error::create(302, "need 3 numbers", &v);
            *member = {v[0].get<double>(), v[1].get<double>(), v[2].get<double>()};
          },
          [member]() {
            return json::array({member->x(), member->y(), member->z()});
          }};
}

std::vector<Binding> SensorBindings(SensorEffects* s) {
  return {Bind("psf_sigma_px", &s->psf_sigma_px),
          Bind("motion_blur", &s->motion_blur),
          Bind("motion_blur_px", &s->motion_blur_px),
          Bind("vignetting", &s->vignetting),
          Bind("vignetting_strength", &s->vignetting_strength),
          Bind("gain_drift", &s->gain_drift),
          Bind("gain_drift_fraction", &s->gain_drift_fraction),
          Bind("offset_drift_fraction", &s->offset_drift_fraction),
          Bind("agc_period_s", &s->agc_period_s),
          Bind("agc_gain_jump_fraction", &s->agc_gain_jump_fraction),
          Bind("agc_offset_jump_fraction", &s->agc_offset_jump_fraction),
          Bind("noise", &s->noise),
          Bind("noise_psnr_db", &s->noise_psnr_db),
          Bind("column_noise", &s->column_noise),
          Bind("column_noise_fraction", &s->column_noise_fraction),
          Bind("dead_pixels", &s->dead_pixels),
          Bind("dead_pixel_fraction", &s->dead_pixel_fraction),
          Bind("bit_depth", &s->bit_depth)};
}

std::vector<Binding> CameraBindings(CameraModel* c) {
  return {Bind("width", &c->width),
          Bind("height", &c->height),
          Bind("fx", &c->fx),
          Bind("fy", &c->fy),
          Bind("cx", &c->cx),
          Bind("cy", &c->cy),
          Bind("distortion", &c->distortion),
          BindVector3("boresight_deg", &c->boresight_deg),
          BindVector3("lever_arm_m", &c->lever_arm_m)};
}

std::vector<Binding> OptionBindings(SynthOptions* o) {
  return {Bind("ground_path", &o->ground_path),
          Bind("ground_m_per_source_px", &o->ground_m_per_source_px),
          Bind("detail_contrast", &o->detail_contrast),
          Bind("origin_lat_deg", &o->origin_lat_deg),
          Bind("origin_lon_deg", &o->origin_lon_deg),
          Bind("ground_height_m", &o->ground_height_m),
          Bind("seed", &o->seed),
          Bind("frame_count", &o->frame_count),
          Bind("fps", &o->fps),
          Bind("altitude_m", &o->altitude_m),
          Bind("heading_deg", &o->heading_deg),
          Bind("speed_mps", &o->speed_mps),
          Bind("frames_per_sweep", &o->frames_per_sweep),
          Bind("sweep_step_deg", &o->sweep_step_deg),
          Bind("sweep_centre_deg", &o->sweep_centre_deg),
          Bind("zigzag", &o->zigzag),
          Bind("along_sweep_overlap", &o->along_sweep_overlap),
          Bind("between_sweep_overlap", &o->between_sweep_overlap),
          Bind("attitude_wobble_deg", &o->attitude_wobble_deg),
          Bind("wobble_period_s", &o->wobble_period_s),
          Bind("gsd_m", &o->gsd_m),
          Bind("position_sigma_m", &o->position_sigma_m),
          BindVector3("position_bias_m", &o->position_bias_m),
          Bind("attitude_sigma_deg", &o->attitude_sigma_deg),
          BindVector3("attitude_bias_deg", &o->attitude_bias_deg),
          Bind("gimbal_sigma_deg", &o->gimbal_sigma_deg),
          Bind("time_offset_s", &o->time_offset_s),
          Bind("ground_cache_mb", &o->ground_cache_mb)};
}

void ReadObject(const json& doc, const std::vector<Binding>& bindings, const std::string& source,
                const std::string& prefix) {
  if (!doc.is_object()) {
    throw InputError({source, 0, 0, prefix}, "expected a JSON object", "see docs/simulator.md");
  }
  for (const auto& item : doc.items()) {
    const std::string name = prefix.empty() ? item.key() : prefix + "." + item.key();
    const Binding* found = nullptr;
    for (const Binding& b : bindings) {
      if (b.key == item.key()) found = &b;
    }
    if (found == nullptr) {
      throw InputError({source, 0, 0, name}, "unknown key '" + name + "'",
                       "remove it or correct its spelling (docs/simulator.md lists the keys)");
    }
    if (item.value().is_null()) continue;  // null: keep the default (JSON has no NaN).
    try {
      found->read(item.value());
    } catch (const json::exception& e) {
      throw InputError({source, 0, 0, name}, "key '" + name + "' has the wrong type",
                       "see docs/simulator.md for its type");
    }
  }
}

json WriteObject(const std::vector<Binding>& bindings) {
  json doc = json::object();
  for (const Binding& b : bindings) {
    json v = b.write();
    if (v.is_number_float() && !std::isfinite(v.get<double>())) v = nullptr;
    doc[b.key] = v;
  }
  return doc;
}

}  // namespace

bool SynthOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& why) {
    if (error) *error = why;
    return false;
  };
  auto positive = [](double v) { return std::isfinite(v) && v > 0; };
  if (frame_count < 1) return fail("frame_count must be at least 1");
  if (!positive(fps)) return fail("fps must be positive");
  if (!positive(altitude_m)) return fail("altitude_m must be positive");
  if (frames_per_sweep < 1) return fail("frames_per_sweep must be at least 1");
  if (!(along_sweep_overlap >= 0 && along_sweep_overlap < 0.9)) {
    return fail("along_sweep_overlap must be in [0, 0.9)");
  }
  if (!(between_sweep_overlap >= 0 && between_sweep_overlap < 0.9)) {
    return fail("between_sweep_overlap must be in [0, 0.9)");
  }
  if (!(speed_mps >= 0) || !(sweep_step_deg >= 0) || !(gsd_m >= 0)) {
    return fail("speed_mps, sweep_step_deg and gsd_m must be >= 0 (0: derived)");
  }
  if (!(ground_m_per_source_px >= 0)) return fail("ground_m_per_source_px must be >= 0");
  if (!(detail_contrast >= 0 && detail_contrast < 1))
    return fail("detail_contrast must be in [0, 1)");
  if (std::isfinite(origin_lat_deg) != std::isfinite(origin_lon_deg)) {
    return fail("give both origin_lat_deg and origin_lon_deg, or neither");
  }
  if (ground_path.empty() && !std::isfinite(origin_lat_deg)) {
    return fail("without ground_path, give origin_lat_deg and origin_lon_deg");
  }
  if (!(position_sigma_m >= 0) || !(attitude_sigma_deg >= 0) || !(gimbal_sigma_deg >= 0)) {
    return fail("error sigmas must be >= 0");
  }
  if (!position_bias_m.allFinite() || !attitude_bias_deg.allFinite() ||
      !std::isfinite(time_offset_s)) {
    return fail("biases and time_offset_s must be finite");
  }
  if (!(std::abs(attitude_wobble_deg) < 10) || !positive(wobble_period_s)) {
    return fail("attitude_wobble_deg must be below 10 and wobble_period_s positive");
  }
  const SensorEffects& s = sensor;
  if (s.bit_depth != 8 && s.bit_depth != 16) return fail("sensor.bit_depth must be 8 or 16");
  if (!(s.psf_sigma_px >= 0 && s.psf_sigma_px < 10)) return fail("sensor.psf_sigma_px in [0, 10)");
  if (!(s.motion_blur_px >= 0 && s.motion_blur_px < 50))
    return fail("sensor.motion_blur_px in [0, 50)");
  if (!(s.vignetting_strength >= 0 && s.vignetting_strength < 1)) {
    return fail("sensor.vignetting_strength in [0, 1)");
  }
  if (!(s.noise_psnr_db > 0 && s.noise_psnr_db < 200))
    return fail("sensor.noise_psnr_db in (0, 200)");
  if (!positive(s.agc_period_s)) return fail("sensor.agc_period_s must be positive");
  if (!(s.dead_pixel_fraction >= 0 && s.dead_pixel_fraction < 0.1)) {
    return fail("sensor.dead_pixel_fraction in [0, 0.1)");
  }
  for (double f : {s.gain_drift_fraction, s.offset_drift_fraction, s.agc_gain_jump_fraction,
                   s.agc_offset_jump_fraction, s.column_noise_fraction}) {
    if (!(f >= 0 && f < 0.5))
      return fail("sensor drift, jump and noise fractions must be in [0, 0.5)");
  }
  if (ground_cache_mb < 1) return fail("ground_cache_mb must be at least 1");
  // The widest look must stay well above the horizon.
  const double half_fov_deg = std::atan(std::hypot(camera.width, camera.height) / 2.0 /
                                        std::max(1e-9, std::min(camera.fx, camera.fy))) *
                              180.0 / M_PI;
  const double step = SweepStepDeg();
  const double widest = std::abs(sweep_centre_deg) + (frames_per_sweep - 1) / 2.0 * step +
                        half_fov_deg + std::abs(attitude_wobble_deg) +
                        std::abs(attitude_bias_deg.x());
  if (widest > 75.0) {
    std::ostringstream why;
    why << "the sweep looks up to " << widest << " degrees off nadir (limit 75)";
    return fail(why.str());
  }
  return true;
}

double SynthOptions::SweepStepDeg() const {
  if (sweep_step_deg > 0) return sweep_step_deg;
  const double fov_x_deg =
      2.0 * std::atan(camera.width / 2.0 / std::max(1e-9, camera.fx)) * 180.0 / M_PI;
  // Consecutive frames of a sweep are also displaced along the track (by speed / fps), which
  // costs a share (1 - between_sweep_overlap) / frames_per_sweep of the overlap area: the
  // angular overlap is raised to compensate, so the area overlap meets the target.
  const double along_shift = (1.0 - between_sweep_overlap) / std::max(1, frames_per_sweep);
  const double angular_overlap = std::min(0.9, along_sweep_overlap / (1.0 - along_shift));
  return (1.0 - angular_overlap) * fov_x_deg;
}

SynthOptions SynthOptions::FromJson(const std::string& json_text, const std::string& source,
                                    const std::string& base_dir) {
  json doc;
  try {
    doc = json::parse(json_text);
  } catch (const json::parse_error& e) {
    throw InputError({source, 0, 0, ""}, std::string("not valid JSON: ") + e.what(),
                     "fix the JSON syntax");
  } catch (const json::exception& e) {
    // E.g. out_of_range for a number beyond double range ("1e999").
    throw InputError({source, 0, 0, ""}, std::string("not valid JSON: ") + e.what(),
                     "fix the JSON (numbers must fit a double)");
  }
  SynthOptions o;
  json top = doc;
  json sensor, camera;
  if (top.is_object() && top.contains("sensor")) {
    sensor = top["sensor"];
    top.erase("sensor");
  }
  if (top.is_object() && top.contains("camera")) {
    camera = top["camera"];
    top.erase("camera");
  }
  ReadObject(top, OptionBindings(&o), source, "");
  if (!sensor.is_null()) ReadObject(sensor, SensorBindings(&o.sensor), source, "sensor");
  if (!camera.is_null()) {
    ReadObject(camera, CameraBindings(&o.camera), source, "camera");
    if (!camera.contains("cx")) o.camera.cx = (o.camera.width - 1) / 2.0;
    if (!camera.contains("cy")) o.camera.cy = (o.camera.height - 1) / 2.0;
    if (!camera.contains("fy")) o.camera.fy = o.camera.fx;
  }
  if (!o.ground_path.empty() && !base_dir.empty() &&
      std::filesystem::path(o.ground_path).is_relative()) {
    o.ground_path = (std::filesystem::path(base_dir) / o.ground_path).lexically_normal().string();
  }
  std::string problem;
  if (!o.IsValid(&problem)) throw InputError({source, 0, 0, ""}, problem, "see docs/simulator.md");
  return o;
}

SynthOptions SynthOptions::LoadJson(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError({path, 0, 0, ""}, "cannot open the flight file", "check the path");
  std::stringstream text;
  text << in.rdbuf();
  return FromJson(text.str(), path, std::filesystem::path(path).parent_path().string());
}

std::string SynthOptions::ToJson() const {
  SynthOptions copy = *this;
  json doc = WriteObject(OptionBindings(&copy));
  doc["sensor"] = WriteObject(SensorBindings(&copy.sensor));
  doc["camera"] = WriteObject(CameraBindings(&copy.camera));
  return doc.dump(2);
}

}  // namespace irmosaic
