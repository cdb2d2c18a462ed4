#pragma once

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
#include "irmosaic/map_fusion.h"
#include "irmosaic/pos.h"
#include "irmosaic/tile_store.h"

namespace irmosaic {

// Configuration of a whole mosaicking run: frames + POS in, a live georeferenced store out.
struct MosaickerOptions {
  std::string store_path;  // The output store folder (e.g. out/flight.irmosaic).
  TileStoreOptions::Mode mode = TileStoreOptions::Mode::kCreate;
  // Mosaic ground sample distance, metres; 0: the camera's nadir GSD at the first frame's
  // height above the ground (rounded to 3 significant digits).
  double gsd_m = 0.0;
  // Flight origin (the mosaic plane's tangent point); NaN: the first POS record.
  double origin_lat_deg = std::numeric_limits<double>::quiet_NaN();
  double origin_lon_deg = std::numeric_limits<double>::quiet_NaN();
  double ground_height_m = 0.0;         // Ellipsoidal height of the ground.
  double pos_position_sigma_m = 2.0;    // POS accuracy (1 sigma) per axis.
  double pos_attitude_sigma_deg = 0.3;  // POS accuracy (1 sigma) per angle.
  double search_radius_px = 64.0;       // SCD search around the POS prediction.
  double max_range_m = 30000.0;         // Ground farther than this is clipped off a frame.
  double publish_interval_s = 0.25;     // How often the store publishes a new generation.
  int tile_size = 512;
  std::string compression = "ZSTD";
  FusionOptions fusion;

  // False with a message naming the option when one is out of range.
  bool IsValid(std::string* error) const;
};

// What happened to one pushed frame.
struct PushResult {
  enum class Status { kPlaced, kSkipped };
  Status status = Status::kSkipped;
  std::string reason;        // Why skipped (no POS, ray above the horizon, bad image...).
  std::string warning;       // Placed with a caveat (ground beyond max_range_m clipped off).
  FramePlacement placement;  // Valid when placed.
  bool placed() const { return status == Status::kPlaced; }
};

// Figures of a run so far.
struct MosaickerSummary {
  int64_t frames_pushed = 0;
  int64_t frames_placed = 0;
  int64_t frames_registered = 0;
  int64_t frames_pos_only = 0;
  int64_t frames_skipped = 0;
  int64_t generations_published = 0;
  double publish_latency_p50_s = 0.0;  // Frame pushed -> its generation published on disk.
  double publish_latency_p99_s = 0.0;
  double publish_latency_max_s = 0.0;
  double gsd_m = 0.0;
  double origin_lat_deg = 0.0, origin_lon_deg = 0.0;
  FusionStats fusion;
};

// The whole pipeline as one object: POS lookup, correction homography, orthorectification,
// registration to neighbours (SCD + fast LSM + RANSAC), map fusion with the background
// optimizer, and the live tiled store. Used by `irmosaic run` and by GIS pipelines.
//
//   Mosaicker m(options, CameraModel::LoadJson("camera.json"), PosTrack::LoadCsv("pos.csv"));
//   for (...) m.Push(index, time_s, image);   // images: CV_8U, CV_16U or CV_32F, one channel
//   m.Finish();                               // last solve, final publish
//
// Thread-safety: Push/Finish from one thread; summary()/Placements() from any.
class IRMOSAIC_EXPORT Mosaicker {
 public:
  // Throws InputError on invalid options; the store opens at the first placed frame.
  Mosaicker(MosaickerOptions options, CameraModel camera, PosTrack pos);
  ~Mosaicker();
  Mosaicker(const Mosaicker&) = delete;
  Mosaicker& operator=(const Mosaicker&) = delete;

  // Places a frame taken at time_s (POS clock). A frame that cannot be placed is skipped with
  // a reason (never an exception for bad frames); store errors throw OutputError.
  PushResult Push(int64_t index, double time_s, const cv::Mat& image);

  // While true, pushed frames rebuild the fusion state but are not painted (resume replay).
  void SetReplay(bool replay);

  // Last solve, re-render, final publish; throws OutputError if the store cannot be written.
  void Finish();

  // Asks the store to publish now (non-blocking).
  void RequestPublish();

  // Index of the last frame in the published application state of a resumed store (-1: none).
  int64_t resumed_last_index() const;

  MosaickerSummary summary() const;
  std::vector<FramePlacement> Placements() const;
  // Writes the placements JSON (docs/formats.md) that `irmosaic eval` scores.
  void WritePlacements(const std::string& path) const;
  // The store (null before the first placed frame).
  TileStore* store();

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace irmosaic
