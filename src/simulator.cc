// FlightSimulator: true poses, logged POS with errors, rendering and sensor effects.
#include "irmosaic/simulator.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "bilinear_warp.h"
#include "irmosaic/error.h"

namespace irmosaic {
namespace {

constexpr double kDeg = M_PI / 180.0;

uint64_t Mix(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

// Deterministic streams of random numbers keyed by (seed, stream, index): the same on every
// platform (no std:: distributions, whose algorithms differ between standard libraries).
class Stream {
 public:
  Stream(uint64_t seed, uint64_t stream, uint64_t index)
      : state_(Mix(Mix(seed ^ 0x5851F42D4C957F2Dull) ^ Mix(stream * 0x9E37ull + 1) ^
                   Mix(index + 0xABCDull))) {}
  double Uniform() {  // [0, 1)
    state_ = Mix(state_);
    return static_cast<double>(state_ >> 11) / 9007199254740992.0;
  }
  double Symmetric() { return 2.0 * Uniform() - 1.0; }  // [-1, 1)
  double Normal() {                                     // Box-Muller.
    const double u1 = std::max(Uniform(), 1e-300), u2 = Uniform();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * M_PI * u2);
  }
  uint64_t Bits() { return state_ = Mix(state_); }

 private:
  uint64_t state_;
};

enum StreamId : uint64_t { kPosError = 1, kWobble, kGain, kAgc, kNoise, kColumns, kDead };

// Gaussian table size for the sensor noise: 2^16 floats (256 KB) stay in the L2 cache; the
// table lookup was the digitisation's main cost with 2^18 (1 MB).
constexpr int kTableBits = 16;

double FullScale(int bit_depth) { return bit_depth == 8 ? 255.0 : 65535.0; }

// Symmetric box of length `length` px (fractional ends) convolved with a Gaussian.
std::vector<float> BlurKernel(double length, double sigma) {
  std::vector<double> box;
  const int r = static_cast<int>(std::ceil(length / 2.0 - 0.5 + 1e-9));
  for (int x = -r; x <= r; ++x) {
    const double lo = std::max(x - 0.5, -length / 2.0), hi = std::min(x + 0.5, length / 2.0);
    box.push_back(std::max(0.0, hi - lo));
  }
  if (length <= 0.0) box = {1.0};
  std::vector<double> gauss = {1.0};
  if (sigma > 0.0) {
    const int g = static_cast<int>(std::ceil(3.0 * sigma));
    gauss.clear();
    for (int x = -g; x <= g; ++x) gauss.push_back(std::exp(-0.5 * x * x / (sigma * sigma)));
  }
  std::vector<double> k(box.size() + gauss.size() - 1, 0.0);
  for (size_t i = 0; i < box.size(); ++i) {
    for (size_t j = 0; j < gauss.size(); ++j) k[i + j] += box[i] * gauss[j];
  }
  double sum = 0.0;
  for (double v : k) sum += v;
  std::vector<float> out;
  for (double v : k) out.push_back(static_cast<float>(v / sum));
  return out;
}

double PolygonOverlap(const std::array<Eigen::Vector2d, 4>& a,
                      const std::array<Eigen::Vector2d, 4>& b) {
  std::vector<cv::Point2f> pa, pb, inter;
  for (const auto& p : a) pa.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()));
  for (const auto& p : b) pb.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()));
  const double area_i = cv::intersectConvexConvex(pa, pb, inter, true);
  const double mean_area = 0.5 * (cv::contourArea(pa) + cv::contourArea(pb));
  return mean_area > 0 ? std::max(0.0, area_i) / mean_area : 0.0;
}

}  // namespace

FlightSimulator::FlightSimulator(SynthOptions options) : options_(std::move(options)) {
  std::string problem;
  if (!options_.IsValid(&problem)) {
    throw InputError({"synth options", 0, 0, ""}, problem, "see docs/simulator.md");
  }
  options_.camera.Validate("synth options camera");
  ground_ = std::make_unique<SyntheticGround>(options_);
  frame_ = std::make_unique<LocalFrame>(ground_->origin_lat_deg(), ground_->origin_lon_deg());
  grid_.gsd_m = options_.gsd_m > 0 ? options_.gsd_m : options_.altitude_m / options_.camera.fx;
  flat_ground_ = FlatGround(options_.ground_height_m);
  ground_->Attach(*frame_, grid_);

  const CameraModel& cam = options_.camera;
  const int n = options_.frames_per_sweep;
  sweep_step_deg_ = options_.SweepStepDeg();
  double min_abs_angle = 1e9;
  for (int k = 0; k < n; ++k) {
    min_abs_angle = std::min(
        min_abs_angle, std::abs(options_.sweep_centre_deg + (k - (n - 1) / 2.0) * sweep_step_deg_));
  }
  if (options_.speed_mps > 0) {
    speed_mps_ = options_.speed_mps;
  } else {
    // Along-track length of the frame nearest nadir; the sweep must not advance more than
    // (1 - overlap) of it between two looks at the same angle.
    const double along_m =
        options_.altitude_m / std::cos(min_abs_angle * kDeg) * cam.height / cam.fy;
    const double frames_between_looks = options_.zigzag ? 2.0 * n - 1.0 : n;
    speed_mps_ =
        (1.0 - options_.between_sweep_overlap) * along_m * options_.fps / frames_between_looks;
  }
  const double heading = options_.heading_deg * kDeg;
  direction_enu_ = {std::sin(heading), std::cos(heading)};
  const double mid_time = (options_.frame_count - 1) / (2.0 * options_.fps);
  start_enu_m_ = -direction_enu_ * speed_mps_ * mid_time;

  // Fixed sensor patterns.
  const SensorEffects& s = options_.sensor;
  const double full = FullScale(s.bit_depth);
  vignetting_gain_ = cv::Mat(cam.height, cam.width, CV_32F, cv::Scalar(1.0f));
  if (s.vignetting) {
    const double r_corner = std::hypot(std::max(cam.cx, cam.width - 1 - cam.cx),
                                       std::max(cam.cy, cam.height - 1 - cam.cy));
    for (int y = 0; y < cam.height; ++y) {
      float* row = vignetting_gain_.ptr<float>(y);
      for (int x = 0; x < cam.width; ++x) {
        const double r = std::hypot(x - cam.cx, y - cam.cy) / r_corner;
        row[x] = static_cast<float>(1.0 - s.vignetting_strength * r * r);
      }
    }
  }
  column_offset_ = cv::Mat(cam.height, cam.width, CV_32F, cv::Scalar(0.0f));
  if (s.column_noise) {
    Stream rng(options_.seed, kColumns, 0);
    cv::Mat row(1, cam.width, CV_32F);
    for (int x = 0; x < cam.width; ++x) {
      row.at<float>(0, x) = static_cast<float>(rng.Normal() * s.column_noise_fraction * full);
    }
    cv::repeat(row, cam.height, 1, column_offset_);
  }
  if (s.dead_pixels) {
    Stream rng(options_.seed, kDead, 0);
    const int count = static_cast<int>(std::lround(s.dead_pixel_fraction * cam.width * cam.height));
    for (int i = 0; i < count; ++i) {
      // Two statements: the order of a call's arguments is unspecified (GCC takes the last
      // first, Clang the first), and the simulator draws the same pixels whatever the compiler.
      const int hot = static_cast<int>(rng.Bits() & 1);
      dead_pixels_.emplace_back(static_cast<int>(rng.Bits() % (cam.width * cam.height)), hot);
    }
  }
  if (s.noise) {
    Stream rng(options_.seed, kNoise, ~0ull);
    gaussian_table_.resize(size_t{1} << kTableBits);
    for (float& v : gaussian_table_) v = static_cast<float>(rng.Normal());
  }
  if (cam.HasDistortion()) {
    // Undistorted position of every render pixel (the image plus the blur margin), once.
    const int m = RenderMargin();
    undistort_map_x_.create(cam.height + 2 * m, cam.width + 2 * m, CV_64F);
    undistort_map_y_.create(cam.height + 2 * m, cam.width + 2 * m, CV_64F);
    for (int y = 0; y < undistort_map_x_.rows; ++y) {
      for (int x = 0; x < undistort_map_x_.cols; ++x) {
        const Eigen::Vector2d u = cam.Undistort({x - m, y - m});
        undistort_map_x_.at<double>(y, x) = u.x();
        undistort_map_y_.at<double>(y, x) = u.y();
      }
    }
  }
  summary_ = Summarise();
}

FlightSimulator::~FlightSimulator() = default;

int FlightSimulator::RenderMargin() const {
  const SensorEffects& s = options_.sensor;
  const size_t kx = BlurKernel(s.motion_blur ? s.motion_blur_px : 0.0, s.psf_sigma_px).size();
  const size_t ky = BlurKernel(0.0, s.psf_sigma_px).size();
  return static_cast<int>(std::max(kx, ky) / 2) + 1;
}

double FlightSimulator::SweepAngleDeg(int index) const {
  const int n = options_.frames_per_sweep;
  const int sweep = index / n;
  int k = index % n;
  if (options_.zigzag && sweep % 2 == 1) k = n - 1 - k;
  return options_.sweep_centre_deg + (k - (n - 1) / 2.0) * sweep_step_deg_;
}

PosRecord FlightSimulator::TruePos(int index) const {
  PosRecord r;
  r.time_s = index / options_.fps;
  const Eigen::Vector2d en = start_enu_m_ + direction_enu_ * speed_mps_ * r.time_s;
  const Eigen::Vector3d geo = frame_->GeodeticFromEnu({en.x(), en.y(), 0.0});
  r.lat_deg = geo.x();
  r.lon_deg = geo.y();
  r.height_m = options_.ground_height_m + options_.altitude_m;
  Stream phases(options_.seed, kWobble, 0);
  const double w = options_.attitude_wobble_deg, p = options_.wobble_period_s;
  const double t = r.time_s;
  r.roll_deg = w * std::sin(2 * M_PI * t / p + 2 * M_PI * phases.Uniform());
  r.pitch_deg = 0.6 * w * std::sin(2 * M_PI * t / (1.3 * p) + 2 * M_PI * phases.Uniform());
  r.yaw_deg = options_.heading_deg +
              0.4 * w * std::sin(2 * M_PI * t / (0.7 * p) + 2 * M_PI * phases.Uniform());
  r.gimbal_roll_deg = SweepAngleDeg(index);
  return r;
}

PosRecord FlightSimulator::MeasuredPosRecord(int index) const {
  const PosRecord truth = TruePos(index);
  PosRecord r = truth;
  Stream rng(options_.seed, kPosError, static_cast<uint64_t>(index));
  const Eigen::Vector3d enu_true = frame_->EnuFromGeodetic(truth.lat_deg, truth.lon_deg, 0.0);
  Eigen::Vector3d error = options_.position_bias_m;
  for (int a = 0; a < 3; ++a) error[a] += options_.position_sigma_m * rng.Normal();
  const Eigen::Vector3d geo =
      frame_->GeodeticFromEnu(enu_true + Eigen::Vector3d(error.x(), error.y(), 0.0));
  r.lat_deg = geo.x();
  r.lon_deg = geo.y();
  r.height_m = truth.height_m + error.z();
  const double sa = options_.attitude_sigma_deg;
  r.roll_deg += options_.attitude_bias_deg.x() + sa * rng.Normal();
  r.pitch_deg += options_.attitude_bias_deg.y() + sa * rng.Normal();
  r.yaw_deg += options_.attitude_bias_deg.z() + sa * rng.Normal();
  r.gimbal_roll_deg += options_.gimbal_sigma_deg * rng.Normal();
  r.time_s = truth.time_s + options_.time_offset_s;
  return r;
}

Eigen::Matrix3d FlightSimulator::TrueMosaicFromImage(int index) const {
  const FrameGeometry g = ComputeFrameGeometry(options_.camera, PoseFromRecord(TruePos(index)),
                                               *frame_, grid_, flat_ground_);
  if (!g.ok) {
    throw InputError({"synth options", 0, 0, ""},
                     "frame " + std::to_string(index) + " cannot be placed: " + g.problem,
                     "lower the sweep angles or raise the altitude");
  }
  return g.mosaic_from_image;
}

PosTrack FlightSimulator::MeasuredPos() const {
  std::vector<PosRecord> records;
  records.reserve(options_.frame_count);
  for (int i = 0; i < options_.frame_count; ++i) records.push_back(MeasuredPosRecord(i));
  return PosTrack::FromRecords(std::move(records), "simulated POS", PosTrack::Options());
}

PosTrack FlightSimulator::TruePosTrack() const {
  std::vector<PosRecord> records;
  records.reserve(options_.frame_count);
  for (int i = 0; i < options_.frame_count; ++i) records.push_back(TruePos(i));
  return PosTrack::FromRecords(std::move(records), "simulated true POS", PosTrack::Options());
}

SimFrame FlightSimulator::Render(int index) const {
  if (index < 0 || index >= options_.frame_count) {
    throw InputError({"Render", 0, 0, "index"},
                     "frame " + std::to_string(index) + " is outside the flight",
                     "ask for 0 .. frame_count - 1");
  }
  const CameraModel& cam = options_.camera;
  const SensorEffects& s = options_.sensor;
  SimFrame out;
  out.index = index;
  out.time_s = index / options_.fps;
  out.true_pos = TruePos(index);
  out.measured_pos = MeasuredPosRecord(index);
  out.true_mosaic_from_image = TrueMosaicFromImage(index);
  const Eigen::Matrix3d& h = out.true_mosaic_from_image;

  // Render with a margin so the blur at the image border sees real ground.
  const std::vector<float> kx = BlurKernel(s.motion_blur ? s.motion_blur_px : 0.0, s.psf_sigma_px);
  const std::vector<float> ky = BlurKernel(0.0, s.psf_sigma_px);
  const int margin = RenderMargin();
  const int rw = cam.width + 2 * margin, rh = cam.height + 2 * margin;
  // Render pixel (xr, yr) is image pixel (xr - margin, yr - margin).
  Eigen::Matrix3d image_from_render = Eigen::Matrix3d::Identity();
  image_from_render(0, 2) = image_from_render(1, 2) = -margin;

  cv::Mat map_x, map_y;  // Only with distortion: mosaic coordinates of each render pixel.
  Eigen::Vector2d lo(1e300, 1e300), hi(-1e300, -1e300);
  if (undistort_map_x_.empty()) {
    for (const Eigen::Vector2d& c :
         {Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(rw - 0.5, -0.5),
          Eigen::Vector2d(-0.5, rh - 0.5), Eigen::Vector2d(rw - 0.5, rh - 0.5)}) {
      const Eigen::Vector2d m = ApplyHomography(h * image_from_render, c);
      lo = lo.cwiseMin(m);
      hi = hi.cwiseMax(m);
    }
  } else {
    // Distorted pixels: undistort (map outside the image extrapolated by the border row), then H.
    map_x.create(rh, rw, CV_32F);
    map_y.create(rh, rw, CV_32F);
    for (int y = 0; y < rh; ++y) {
      for (int x = 0; x < rw; ++x) {
        const Eigen::Vector2d u(undistort_map_x_.at<double>(y, x),
                                undistort_map_y_.at<double>(y, x));
        const Eigen::Vector2d m = ApplyHomography(h, u);
        map_x.at<float>(y, x) = static_cast<float>(m.x());
        map_y.at<float>(y, x) = static_cast<float>(m.y());
        lo = lo.cwiseMin(m);
        hi = hi.cwiseMax(m);
      }
    }
  }
  // Ground samples needed: sample j is centred at mosaic coordinate step * j + (step - 1) / 2.
  constexpr double kStep = SyntheticGround::kSampleStep;
  const double sample_offset = (kStep - 1.0) / 2.0;
  const int64_t col0 = static_cast<int64_t>(std::floor((lo.x() - sample_offset) / kStep)) - 2;
  const int64_t row0 = static_cast<int64_t>(std::floor((lo.y() - sample_offset) / kStep)) - 2;
  const double span_x = std::ceil((hi.x() - sample_offset) / kStep) - static_cast<double>(col0) + 3;
  const double span_y = std::ceil((hi.y() - sample_offset) / kStep) - static_cast<double>(row0) + 3;
  if (span_x * span_y > 16e6) {
    throw InputError({"synth options", 0, 0, ""},
                     "frame " + std::to_string(index) + " covers an absurd ground area",
                     "lower the sweep angles or coarsen gsd_m");
  }
  // Scratch reused across frames (per thread): no allocation or page faults once warm.
  thread_local std::vector<float> patch_storage;
  thread_local cv::Mat warped, blurred;
  const size_t patch_size = static_cast<size_t>(span_x) * static_cast<size_t>(span_y);
  if (patch_storage.size() < patch_size) patch_storage.resize(patch_size + patch_size / 2);
  cv::Mat patch(static_cast<int>(span_y), static_cast<int>(span_x), CV_32F, patch_storage.data());
  ground_->Fill(col0, row0, static_cast<int>(span_x), static_cast<int>(span_y), &patch);
  // Patch sample coordinates of a mosaic pixel coordinate.
  Eigen::Matrix3d patch_from_mosaic = Eigen::Matrix3d::Identity();
  patch_from_mosaic(0, 0) = patch_from_mosaic(1, 1) = 1.0 / kStep;
  patch_from_mosaic(0, 2) = -sample_offset / kStep - static_cast<double>(col0);
  patch_from_mosaic(1, 2) = -sample_offset / kStep - static_cast<double>(row0);
  if (map_x.empty()) {
    const Eigen::Matrix3d m = patch_from_mosaic * h * image_from_render;
    cv::Matx33d mcv;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) mcv(r, c) = m(r, c);
    }
    sim::WarpBilinear(patch, mcv, cv::Size(rw, rh), &warped);
  } else {
    map_x.convertTo(map_x, CV_32F, 1.0 / kStep, patch_from_mosaic(0, 2));
    map_y.convertTo(map_y, CV_32F, 1.0 / kStep, patch_from_mosaic(1, 2));
    cv::remap(patch, warped, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  }
  cv::Mat signal = warped;
  if (kx.size() > 1 || ky.size() > 1) {
    cv::sepFilter2D(warped, blurred, CV_32F, cv::Mat(kx), cv::Mat(ky), cv::Point(-1, -1), 0,
                    cv::BORDER_REPLICATE);
    signal = blurred;
  }
  signal = signal(cv::Rect(margin, margin, cam.width, cam.height));

  // Digitise: counts = full * (0.05 + 0.9 * (gain * vignetting * signal + offset)) + columns
  // + noise. The 5 % floor and 90 % span leave head room for gain jumps before clipping.
  const double full = FullScale(s.bit_depth);
  double gain = 1.0, offset = 0.0;
  if (s.gain_drift) {
    Stream phases(options_.seed, kGain, 0);
    const double t = out.time_s;
    gain =
        1.0 + s.gain_drift_fraction * std::sin(2 * M_PI * t / 23.0 + 2 * M_PI * phases.Uniform());
    offset = s.offset_drift_fraction * std::sin(2 * M_PI * t / 31.0 + 2 * M_PI * phases.Uniform());
    Stream agc(options_.seed, kAgc, static_cast<uint64_t>(std::floor(t / s.agc_period_s)));
    gain *= 1.0 + s.agc_gain_jump_fraction * agc.Symmetric();
    offset += s.agc_offset_jump_fraction * agc.Symmetric();
  }
  // One pass (this stage is a third of the frame's cost when done as separate OpenCV calls).
  // Noise: Gaussian samples drawn from a table of unit normals by a per-pixel xorshift, the
  // same on every platform and a fresh draw per pixel and frame.
  const float scale = static_cast<float>(0.9 * full * gain);
  const float base = static_cast<float>(full * (0.05 + 0.9 * offset));
  const float sigma =
      s.noise ? static_cast<float>(full * std::pow(10.0, -s.noise_psnr_db / 20.0)) : 0.0f;
  uint64_t state = Stream(options_.seed, kNoise, static_cast<uint64_t>(index)).Bits() | 1;
  out.image.create(cam.height, cam.width, s.bit_depth == 8 ? CV_8U : CV_16U);
  // Specialised per output type and noise on/off so the inner loop has no branches.
  auto digitise = [&]<typename T, bool kNoisy>() {
    for (int y = 0; y < cam.height; ++y) {
      const float* in = signal.ptr<float>(y);
      const float* vig = vignetting_gain_.ptr<float>(y);
      const float* col = column_offset_.ptr<float>(y);
      T* dst = out.image.ptr<T>(y);
      for (int c = 0; c < cam.width; ++c) {
        float v = in[c] * vig[c] * scale + base + col[c];
        if constexpr (kNoisy) {
          state ^= state >> 12;
          state ^= state << 25;
          state ^= state >> 27;
          v += sigma * gaussian_table_[(state * 0x2545F4914F6CDD1Dull) >> (64 - kTableBits)];
        }
        dst[c] = cv::saturate_cast<T>(v);
      }
    }
  };
  if (s.bit_depth == 8) {
    s.noise ? digitise.operator()<uint8_t, true>() : digitise.operator()<uint8_t, false>();
  } else {
    s.noise ? digitise.operator()<uint16_t, true>() : digitise.operator()<uint16_t, false>();
  }
  for (const auto& [offset_px, stuck_high] : dead_pixels_) {
    const int y = offset_px / cam.width, x = offset_px % cam.width;
    if (s.bit_depth == 8) {
      out.image.at<uint8_t>(y, x) = stuck_high ? 255 : 0;
    } else {
      out.image.at<uint16_t>(y, x) = stuck_high ? 65535 : 0;
    }
  }
  return out;
}

FlightSummary FlightSimulator::Summarise() const {
  FlightSummary sum;
  const int n = options_.frames_per_sweep;
  sum.speed_mps = speed_mps_;
  sum.sweep_step_deg = sweep_step_deg_;
  sum.sweep_min_deg = options_.sweep_centre_deg - (n - 1) / 2.0 * sweep_step_deg_;
  sum.sweep_max_deg = options_.sweep_centre_deg + (n - 1) / 2.0 * sweep_step_deg_;
  sum.sweep_rate_deg_s = sweep_step_deg_ * options_.fps;
  sum.sweep_period_s = n / options_.fps;
  const double half_fov_x = std::atan(options_.camera.width / 2.0 / options_.camera.fx) / kDeg;
  sum.max_off_nadir_deg = std::max(std::abs(sum.sweep_min_deg), std::abs(sum.sweep_max_deg)) +
                          half_fov_x + options_.attitude_wobble_deg;
  sum.gsd_m = grid_.gsd_m;
  sum.flight_length_m = speed_mps_ * (options_.frame_count - 1) / options_.fps;
  // Overlaps measured on footprints of sweeps 2 and 3 (indices exist for any flight length).
  auto footprint = [&](int i) {
    const FrameGeometry g = ComputeFrameGeometry(options_.camera, PoseFromRecord(TruePos(i)),
                                                 *frame_, grid_, flat_ground_);
    if (!g.ok) {
      throw InputError({"synth options", 0, 0, ""},
                       "frame " + std::to_string(i) + " cannot be placed: " + g.problem,
                       "lower the sweep angles or raise the altitude");
    }
    sum.truth_fit_max_px = std::max(sum.truth_fit_max_px, g.fit_max_px);
    return g.footprint_m;
  };
  std::vector<std::array<Eigen::Vector2d, 4>> fp;
  for (int i = 0; i < 3 * n; ++i) fp.push_back(footprint(i));
  double along = 0.0, between = 0.0, between_min = 1.0;
  const int s = 2;
  for (int k = 0; k + 1 < n; ++k) along += PolygonOverlap(fp[s * n + k], fp[s * n + k + 1]);
  for (int k = 0; k < n; ++k) {
    const int i = s * n + k;
    const double angle = SweepAngleDeg(i);
    for (int j = (s - 1) * n; j < s * n; ++j) {
      if (std::abs(SweepAngleDeg(j) - angle) < 1e-9) {
        const double o = PolygonOverlap(fp[i], fp[j]);
        between += o;
        between_min = std::min(between_min, o);
      }
    }
  }
  sum.along_sweep_overlap = n > 1 ? along / (n - 1) : 0.0;
  sum.between_sweep_overlap = between / n;
  sum.between_sweep_overlap_min = between_min;
  return sum;
}

}  // namespace irmosaic
