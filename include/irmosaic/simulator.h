#pragma once

// Simulator of an oblique sweeping infrared camera over a ground image, with ground truth.
//
// The ground is a georeferenced raster laid on the truth's mosaic plane and extended without
// repetition by deterministic fractal terrain (docs/simulator.md). Each frame is rendered
// through the homography of its true pose (ComputeFrameGeometry), so the truth and the pixels
// agree exactly; the POS log the pipeline gets carries configurable errors. Usage:
//
//   SynthOptions options;
//   options.ground_path = "ground.tif";
//   options.frame_count = 300;
//   FlightSimulator sim(options);        // throws InputError on bad options
//   SimFrame f = sim.Render(17);         // any order, deterministic given the seed
//   sim.WriteFlight("out/flight");       // frames/, pos.csv, camera.json, truth.json

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "irmosaic/camera.h"
#include "irmosaic/export.h"
#include "irmosaic/frame_geometry.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/pos.h"

namespace irmosaic {

// Infrared sensor effects applied after rendering; each can be switched off.
struct SensorEffects {
  // Optics: Gaussian point spread function, pixels (0: none).
  double psf_sigma_px = 0.5;
  // Motion blur along the sweep (image x): symmetric box of this length, pixels, centred on the
  // exposure's middle so the truth stays the pose at the frame time.
  bool motion_blur = true;
  double motion_blur_px = 2.0;
  // Vignetting: relative signal loss at the image corners, quadratic in the radius.
  bool vignetting = true;
  double vignetting_strength = 0.2;
  // Gain and offset drift: slow sinusoidal drift plus automatic-gain-control jumps, held for
  // agc_period_s each (a fresh random level every period).
  bool gain_drift = true;
  double gain_drift_fraction = 0.05;    // Amplitude of the slow gain drift (relative).
  double offset_drift_fraction = 0.03;  // Amplitude of the slow offset drift (of full scale).
  double agc_period_s = 2.0;
  double agc_gain_jump_fraction = 0.15;    // AGC gain levels uniform in 1 +- this.
  double agc_offset_jump_fraction = 0.05;  // AGC offset levels uniform in +- this (full scale).
  // Gaussian noise whose PSNR against the noise-free frame, with the output's full scale as
  // peak (65535 or 255), is this many dB.
  bool noise = true;
  double noise_psnr_db = 30.0;
  // Fixed-pattern column noise: one offset per column for the whole flight.
  bool column_noise = true;
  double column_noise_fraction = 0.005;  // Standard deviation, of full scale.
  // Dead pixels stuck at 0 or full scale, at fixed places for the whole flight.
  bool dead_pixels = true;
  double dead_pixel_fraction = 1e-4;
  // Output sample depth: 16 (CV_16U) or 8 (CV_8U).
  int bit_depth = 16;
};

// Everything that defines a simulated flight. Defaults: a realistic oblique sweep, see
// docs/simulator.md for the geometry they produce.
struct SynthOptions {
  // Ground raster: any georeferenced GDAL raster (first three bands mixed to gray, alpha and
  // nodata honoured). Empty: pure fractal terrain around origin_lat/lon_deg.
  std::string ground_path;
  // Ground size of one source pixel in metres; 0 keeps the raster's own georeference. Any
  // other value scales the raster about its centre (its georeference is then only nominal).
  double ground_m_per_source_px = 0.0;
  double detail_contrast = 0.05;  // Std of the fractal detail added at the mosaic scale.
  // Flight origin (truth's mosaic plane); NaN: the centre of the ground raster.
  double origin_lat_deg = std::numeric_limits<double>::quiet_NaN();
  double origin_lon_deg = std::numeric_limits<double>::quiet_NaN();
  double ground_height_m = 0.0;  // Ellipsoidal height of the (flat) ground.

  uint64_t seed = 1;
  int frame_count = 300;
  double fps = 25.0;
  CameraModel camera = DefaultInfraredCamera();

  // Flight: straight line through the origin (its middle frame above it), constant height.
  double altitude_m = 800.0;  // Above the ground.
  double heading_deg = 30.0;  // Track, clockwise from north.
  double speed_mps = 0.0;     // 0: derived from between_sweep_overlap.
  // Sweep: frames_per_sweep frames from one side to the other, stepping sweep_step_deg
  // (0: derived from along_sweep_overlap), centred on sweep_centre_deg. Fly-back (every sweep
  // in the same direction) unless zigzag.
  int frames_per_sweep = 8;
  double sweep_step_deg = 0.0;
  double sweep_centre_deg = 0.0;
  bool zigzag = false;
  double along_sweep_overlap = 0.25;    // Target overlap of consecutive frames of a sweep.
  double between_sweep_overlap = 0.15;  // Target overlap of a frame and the previous sweep's.
  // True attitude is not level: slow sinusoidal roll/pitch/yaw wobble of this amplitude.
  double attitude_wobble_deg = 0.5;
  double wobble_period_s = 7.0;
  double gsd_m = 0.0;  // Truth's mosaic grid; 0: altitude / fx (the nadir pixel).

  // POS errors: independent per frame (white) plus a constant bias.
  double position_sigma_m = 2.0;                                // Per axis E, N, U.
  Eigen::Vector3d position_bias_m = Eigen::Vector3d::Zero();    // E, N, U.
  double attitude_sigma_deg = 0.3;                              // Roll, pitch, yaw each.
  Eigen::Vector3d attitude_bias_deg = Eigen::Vector3d::Zero();  // Roll, pitch, yaw.
  double gimbal_sigma_deg = 0.0;                                // Error of the logged sweep angle.
  double time_offset_s = 0.0;                                   // POS clock minus frame clock.

  SensorEffects sensor;
  size_t ground_cache_mb = 128;  // Bound on the memory of generated ground tiles.

  // False with a reason when an option is out of range.
  bool IsValid(std::string* error) const;
  // The sweep step: sweep_step_deg, or the one along_sweep_overlap implies.
  double SweepStepDeg() const;
  // JSON (docs/simulator.md); unknown keys are errors naming the key. Relative ground paths
  // are resolved against `base_dir`.
  static SynthOptions FromJson(const std::string& json_text, const std::string& source,
                               const std::string& base_dir = "");
  static SynthOptions LoadJson(const std::string& path);
  std::string ToJson() const;
};

// One rendered frame with its truth.
struct SimFrame {
  int index = 0;
  double time_s = 0.0;
  cv::Mat image;           // CV_16U (or CV_8U), camera.width x camera.height.
  PosRecord true_pos;      // The pose the frame was rendered with.
  PosRecord measured_pos;  // The POS record logged for it (errors applied).
  Eigen::Matrix3d true_mosaic_from_image = Eigen::Matrix3d::Identity();  // Truth grid.
};

// Figures of the flight the options produce.
struct FlightSummary {
  double speed_mps = 0.0;
  double sweep_step_deg = 0.0;
  double sweep_min_deg = 0.0, sweep_max_deg = 0.0;
  double sweep_rate_deg_s = 0.0;
  double sweep_period_s = 0.0;
  double max_off_nadir_deg = 0.0;
  double gsd_m = 0.0;
  double along_sweep_overlap = 0.0;    // Realised mean, from footprint polygons.
  double between_sweep_overlap = 0.0;  // Realised mean (min over the frames of a sweep below).
  double between_sweep_overlap_min = 0.0;
  double flight_length_m = 0.0;
  double truth_fit_max_px = 0.0;  // Worst homography-vs-exact-ray departure seen (sampled).
};

// The ground: a georeferenced raster on the truth's mosaic plane plus fractal terrain, as a
// float signal (about 0..1) per mosaic pixel, generated in cached tiles on demand.
class IRMOSAIC_EXPORT SyntheticGround {
 public:
  // Reads the raster (if any); throws InputError when unreadable or not georeferenced.
  explicit SyntheticGround(const SynthOptions& options);
  ~SyntheticGround();
  SyntheticGround(const SyntheticGround&) = delete;
  SyntheticGround& operator=(const SyntheticGround&) = delete;

  // Origin the raster implies (its centre), or the options' origin when given.
  double origin_lat_deg() const;
  double origin_lon_deg() const;
  // The ground is stored at a step of kSampleStep mosaic pixels: sample (j, i) is centred at
  // mosaic pixel coordinates (kSampleStep * j + (kSampleStep - 1) / 2, likewise for i), and
  // between samples the ground is their bilinear interpolation (as frames are rendered). Frame
  // pixels are >= 1 mosaic px and the optics blur them, so finer ground detail would be lost.
  static constexpr int kSampleStep = 2;
  // Must be called once before Fill, with the truth's frame and grid.
  void Attach(const LocalFrame& frame, const MosaicGrid& grid);
  // Fills `out` (CV_32F) with samples [col0, col0 + cols) x [row0, row0 + rows). Thread-safe.
  void Fill(int64_t col0, int64_t row0, int cols, int rows, cv::Mat* out) const;
  // Tiles generated so far (for the benchmark).
  int64_t tiles_generated() const;
  // Bytes of generated tiles held in the cache now (bounded by SynthOptions::ground_cache_mb).
  int64_t cached_bytes() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Options of WriteFlight.
struct WriteFlightOptions {
  std::string image_extension = "tif";  // "tif" or "png" (both lossless, 16 or 8 bit).
  bool write_frames = true;             // False: POS, camera and truth only.
  // Also write the frames as a video here (8-bit, lossless FFV1 in .mkv/.avi, or MJPG when
  // the extension is .mjpg.avi); empty: no video. 16-bit frames keep their top 8 bits.
  std::string video_path;
  // Called after each frame written with (frames done, total).
  std::function<void(int, int)> progress;
};

// A simulated flight: true poses, logged POS, rendered frames and the truth's placements.
class IRMOSAIC_EXPORT FlightSimulator {
 public:
  // Throws InputError on bad options or an unreadable ground raster.
  explicit FlightSimulator(SynthOptions options);
  ~FlightSimulator();
  FlightSimulator(const FlightSimulator&) = delete;
  FlightSimulator& operator=(const FlightSimulator&) = delete;

  int frame_count() const { return options_.frame_count; }
  const SynthOptions& options() const { return options_; }
  const CameraModel& camera() const { return options_.camera; }
  const LocalFrame& frame() const { return *frame_; }
  const MosaicGrid& grid() const { return grid_; }
  const FlightSummary& summary() const { return summary_; }
  const SyntheticGround& ground() const { return *ground_; }

  // True and logged POS records of a frame (cheap, no rendering).
  PosRecord TruePos(int index) const;
  PosRecord MeasuredPosRecord(int index) const;
  // True placement of a frame: undistorted image pixel -> truth mosaic pixel.
  Eigen::Matrix3d TrueMosaicFromImage(int index) const;

  // Renders a frame: deterministic given seed and index, in any order, from any thread.
  // Memory stays bounded however long the flight (ground tiles are cached with a bound).
  SimFrame Render(int index) const;

  // The POS log the pipeline gets: one record per frame, errors applied.
  PosTrack MeasuredPos() const;
  // The true poses as a POS log.
  PosTrack TruePosTrack() const;

  // Writes frames/NNNNNN.<ext>, frames.csv (index,time_s,file), pos.csv (measured),
  // true_pos.csv, camera.json, truth.json (placements format), pos_only.json (placements from
  // the logged POS alone: the baseline), truth_pairs.json (neighbour pairs along and between
  // sweeps with their true base_from_template) and flight.json (the options).
  // Throws OutputError when the folder cannot be written.
  void WriteFlight(const std::string& dir, const WriteFlightOptions& options = {}) const;

 private:
  double SweepAngleDeg(int index) const;
  int RenderMargin() const;  // Pixels rendered around the image so the blur sees real ground.
  FlightSummary Summarise() const;

  SynthOptions options_;
  std::unique_ptr<LocalFrame> frame_;
  MosaicGrid grid_;
  std::unique_ptr<SyntheticGround> ground_;
  FlatGround flat_ground_;
  Eigen::Vector2d start_enu_m_ = Eigen::Vector2d::Zero();
  Eigen::Vector2d direction_enu_ = Eigen::Vector2d::UnitY();
  double speed_mps_ = 0.0;
  double sweep_step_deg_ = 0.0;
  FlightSummary summary_;
  // Fixed sensor patterns (per flight).
  cv::Mat vignetting_gain_;                       // CV_32F, multiplies the signal.
  cv::Mat column_offset_;                         // CV_32F, full frame, counts.
  std::vector<std::pair<int, int>> dead_pixels_;  // (pixel offset, stuck value 0 or 1).
  // Only with lens distortion: undistorted pixel of each render pixel (CV_64F).
  cv::Mat undistort_map_x_, undistort_map_y_;
  std::vector<float> gaussian_table_;  // Unit normal samples for the noise.
};

}  // namespace irmosaic
