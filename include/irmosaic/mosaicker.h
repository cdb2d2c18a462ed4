#pragma once

#include <Eigen/Core>
#include <array>
#include <chrono>
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
#include "irmosaic/orthorectify.h"
#include "irmosaic/pos.h"
#include "irmosaic/registration.h"
#include "irmosaic/tile_store.h"

namespace irmosaic {

// One pair registration of a run as the pipeline saw it (MosaickerOptions::on_pair_registered):
// the two frames' POS orthoimages (mosaic plane, mosaic GSD), the offset POS predicts and the
// search radius given to the registrar, and its result. Views valid during the call only.
struct PairRegistrationRecord {
  int64_t base_index = -1;
  int64_t template_index = -1;
  const OrthoImage* base = nullptr;
  const OrthoImage* templ = nullptr;
  Eigen::Vector2d predicted_offset = Eigen::Vector2d::Zero();  // templ(0,0) in base's pixels.
  double search_radius_px = 0.0;  // Of the try reported: the wide radius if the first failed.
  const PairRegistration* result = nullptr;
};

// Configuration of a whole mosaicking run: frames + POS in, a live georeferenced store out.
// Checked by the Mosaicker constructor (IsValid); an invalid value throws InputError naming it.
struct MosaickerOptions {
  std::string store_path;  // The output store folder (e.g. out/flight.irmosaic).
  TileStoreOptions::Mode mode = TileStoreOptions::Mode::kCreate;
  // Mosaic ground sample distance, metres; 0: the camera's nadir GSD at the first frame's
  // height above the ground (rounded to 3 significant digits).
  double gsd_m = 0.0;
  // Flight origin (the mosaic plane's tangent point); NaN: the first POS record. With an
  // empty POS track (poses given to Push) the origin and gsd_m must be set.
  double origin_lat_deg = std::numeric_limits<double>::quiet_NaN();
  double origin_lon_deg = std::numeric_limits<double>::quiet_NaN();
  double ground_height_m = 0.0;         // Ellipsoidal height of the ground.
  double pos_position_sigma_m = 2.0;    // POS accuracy (1 sigma) per axis.
  double pos_attitude_sigma_deg = 0.3;  // POS accuracy (1 sigma) per angle.
  double search_radius_px = 64.0;       // SCD search around the POS prediction.
  // A pair that fails at search_radius_px is tried once more at this radius (0: not): the POS
  // prediction of a sweep's most oblique frames can be off by more than 64 px (80-97 px in the
  // sample flight's failures), and the coarse match cannot find an offset outside its radius.
  double wide_search_radius_px = 128.0;
  double max_range_m = 30000.0;      // Ground farther than this is clipped off a frame.
  double publish_interval_s = 0.25;  // How often the store publishes a new generation.
  // How often overviews and frames.gpkg follow (TileStoreOptions::overview_interval_s).
  double overview_interval_s = 2.0;
  // The store's writer thread's nice increment (TileStoreOptions::writer_nice, 0..19).
  int writer_nice = 5;
  // How often the store flushes its file system, seconds (TileStoreOptions::sync_interval_s;
  // 0: never).
  double sync_interval_s = 2.0;
  int tile_size = 512;               // Store tile side, pixels: a multiple of 16 in [64, 8192].
  std::string compression = "ZSTD";  // Store tiles: "ZSTD", "DEFLATE", "LZW" or "NONE".
  // Write the extent the POS track foresees for the whole flight into the store
  // (TileStore::SetPlannedBoundsPx), so that QGIS, through the IRMOSAIC plug-in, shows the
  // mosaic grow over it without reopening the layer. Off, or with poses pushed directly, the
  // store's extent is the painted one.
  bool planned_extent = true;
  // Pairs of a new frame registered at once (FusionOptions::registration_threads, which this
  // replaces): 2 registers a frame to its two neighbours on two threads, the same placements.
  // 2 by default since session 16: it is what let the caller take frames at 25 per second on
  // 2 cores in the measurements (with FusionOptions::optimizer_nice 10; one thread needs
  // ~35 CPU ms a frame, at the sensor's 40 ms interval, and fell seconds behind), for ~30 MiB
  // more peak memory (docs/benchmarks.md, "Session 16"). 1: one pair after the other.
  int registration_threads = 2;
  // Every this many pushed frames, Push returns the free pages the C library's heap keeps to
  // the system (glibc malloc_trim; buffers of varying size freed on several threads leave free
  // memory the heap otherwise holds on to and grows over a long flight: docs/benchmarks.md,
  // "Session 8"). 0: never. The call is process-wide.
  int heap_trim_interval_frames = 250;
  // Sets the C library's heap for a long stream when the Mosaicker is made (glibc mallopt,
  // process-wide): buffers under 32 MiB come from the heap instead of mappings of their own,
  // and a free never hands memory back by itself (M_TRIM_THRESHOLD 1 GiB); the periodic trim
  // above does, every heap_trim_interval_frames frames. glibc's default returns the top of a
  // thread's heap on many frees, and the next image-sized buffer faults its pages back in, one
  // per 4 KiB: 1.7 million page faults in 3000 frames, 0.43 million tuned; pipeline CPU
  // 72.7 -> 60.2 ms/frame, peak RSS 695 -> 734 MiB (docs/benchmarks.md, "Session 17"). With
  // heap_trim_interval_frames 0 the heap keeps what it ever held free: turn this off too.
  bool tune_heap = true;
  // The store's memory bound (TileStoreOptions::max_cached_tiles): clean level-0 tiles kept in
  // memory, and twice as many may wait for the writer before painting waits. Each tile is
  // tile_size^2 x (sample size + 1) bytes (768 KiB at 512 and 16 bits); fewer means more tiles
  // read back from disk (docs/benchmarks.md, "Session 12").
  int max_cached_tiles = 64;
  // The optimizer's re-renders reach the disk in slices between publishes, at most this many
  // tiles each, so that a publish carries new frames only (TileStoreOptions::refresh_slice_tiles;
  // 0: with the next publish, as new frames).
  int refresh_slice_tiles = 8;
  // Publishes a re-rendered tile waits unpainted before a slice writes it
  // (TileStoreOptions::refresh_quiet_publishes; 1: after the next publish).
  int refresh_quiet_publishes = 1;
  // Frame images the fusion keeps in memory (FusionOptions::images_in_memory, which this
  // replaces): the newest N; the older ones it still holds for re-rendering (up to the
  // optimization window, 300 frames) wait in an unnamed file in the store folder, deleted with
  // the process. 0 keeps them all in memory (640 KiB each at 640 x 512 x 16 bits). Registration
  // reaches back 8 frames in the bundled sample's sweeps, so with 32 the reads serve the
  // re-renders (docs/benchmarks.md, "Session 13").
  int images_in_memory = 32;
  // With a store, placements of frames that left the optimization window are read back from
  // the store's frozen frames' file (resume_frames.jsonl) by Placements() instead of kept in
  // memory, so memory does not grow with the flight (~0.4 KiB per frame otherwise). true keeps
  // them all in memory.
  bool keep_placements_in_memory = false;
  FusionOptions fusion;
  // How neighbouring frames are registered (SCD + FLSM + RANSAC): PipelineRegistrationOptions()
  // unless changed, e.g. fine.lsm_level.
  PairRegistrationOptions registration = PipelineRegistrationOptions();
  // Diagnostics: called after each pair registration, on the thread that registered it (one
  // of registration_threads), with its inputs and result; copy what is kept. For replaying the
  // pipeline's own pairs (bench/pipeline_pairs_bench) or logging them. Empty: not called.
  std::function<void(const PairRegistrationRecord&)> on_pair_registered;
  // Diagnostics: called each time a frame is painted into the mosaic (its first paint and
  // every re-render after a solve moved it), with the placement it was painted at, on the
  // painting thread (the caller's or the optimizer's; both may call at once). The last call
  // for a frame is where the mosaic shows it, which can lag its latest placement (re-renders
  // are deferred while the output is behind): bench/flight_bench scores both against the
  // truth. Not called while a resume replays frames (nothing is painted). Empty: not called.
  std::function<void(const FramePlacement&)> on_frame_painted;
  // Diagnostics: called once for each frame a publish put on disk, with its index and its
  // publish latency (seconds from its arrival, as given to Push, to the end of that publish:
  // what MosaickerSummary's publish latency quantiles are made of), in push order, on the
  // caller's thread at the end of Push, RequestPublish or Finish. For latency over time in a
  // long run (bench/flight_bench's checkpoints). Empty: not called.
  std::function<void(int64_t index, double latency_s)> on_frame_published;
  // Diagnostics: the store's report of each publish (TileStoreOptions::on_publish), on the
  // store's writer thread. With on_frame_published it traces a frame's latency to its parts.
  // Empty: not called.
  std::function<void(const PublishReport&)> on_publish;

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

// A level-0 window of the current mosaic with what GDAL needs to georeference it.
struct MosaicWindow {
  cv::Rect mosaic_px;                       // The window, mosaic pixels (may reach past the data).
  cv::Mat image;                            // Store pixel type (CV_8U/16U/32F), one channel.
  cv::Mat coverage;                         // CV_8U: 255 where painted, 0 elsewhere.
  std::array<double, 6> geotransform = {};  // GDAL geotransform, mosaic CRS metres.
  std::string crs_wkt;                      // The mosaic CRS (local tangent plane), WKT.
};

// GDAL geotransform of a level-0 window whose top-left pixel is mosaic pixel top_left_px: pixel
// (col, row) is centred on plane (col*gsd, -row*gsd), so its corner is half a pixel off.
IRMOSAIC_EXPORT std::array<double, 6> WindowGeoTransform(double gsd_m, cv::Point top_left_px);

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
//   m.OnPublished([](int64_t generation) { ... });  // optional: each generation on disk
//   for (...) m.Push(index, time_s, image);   // images: CV_8U, CV_16U or CV_32F, one channel
//   MosaicWindow w = m.ReadWindow(m.bounds_px());  // any time after the first placed frame
//   m.Finish();                               // last solve, final publish
//
// Ownership: the Mosaicker owns copies of the options, camera and POS track, the images it
// keeps (pushed images are copied; the caller's buffer may be reused at once), its two
// background threads (fusion optimizer, store writer) and the store; the destructor joins the
// threads (call Finish() first for a final publish). Results (PushResult, MosaicWindow,
// placements, records) are values the caller owns.
// Thread-safety: Push, SetReplay, RequestPublish and Finish from one thread at a time (the
// "producer"); summary(), Placements(), FrameRecords(), ReadWindow(), bounds_px(),
// published_generation() and WaitPublished() from any thread, concurrently with the producer.
class IRMOSAIC_EXPORT Mosaicker {
 public:
  // Throws InputError on invalid options (message names the option) or when the origin and
  // GSD cannot be found (empty POS track without them); the store opens at the first placed
  // frame (at once in resume mode).
  Mosaicker(MosaickerOptions options, CameraModel camera, PosTrack pos);
  ~Mosaicker();
  Mosaicker(const Mosaicker&) = delete;
  Mosaicker& operator=(const Mosaicker&) = delete;

  // Places a frame taken at time_s, its pose interpolated in the POS track. A frame that
  // cannot be placed is skipped with a reason (never an exception for bad frames); store
  // errors throw OutputError.
  PushResult Push(int64_t index, double time_s, const cv::Mat& image);
  // Same with the frame's pose given directly (e.g. from a live POS stream; PoseFromRecord
  // converts a PosRecord); the POS track is not consulted.
  PushResult Push(int64_t index, double time_s, const Pose& pose, const cv::Mat& image);
  // As Push, for a frame that arrived from the sensor at `arrival` (earlier than now when it
  // waited in a queue): the publish latency counts from then.
  PushResult Push(int64_t index, double time_s, const cv::Mat& image,
                  std::chrono::steady_clock::time_point arrival);

  // While true, pushed frames rebuild the fusion state but are not painted (resume replay of a
  // store without a resume record; with one, frames up to resumed_last_index() are replays
  // whatever this says).
  void SetReplay(bool replay);

  // Last solve, re-render, final publish; throws OutputError if the store cannot be written.
  void Finish();

  // Asks the store to publish now (non-blocking).
  void RequestPublish();

  // Called with each newly published generation number (a generation is a consistent state
  // of mosaic.vrt, manifest.json, tiles and frames.gpkg on disk). Runs on the producer thread,
  // at the end of Push/Finish/RequestPublish, for generations published since the last call
  // (several publishes may coalesce into one call with the latest); never concurrently.
  // An exception it throws propagates out of that call. Empty function: none.
  void OnPublished(std::function<void(int64_t generation)> callback);
  // Poll: generation of the last publish on disk (0: nothing published yet).
  int64_t published_generation() const;
  // Blocks until generation `generation` is on disk (e.g. published_generation() + 1 after
  // RequestPublish()); throws OutputError if the store failed or closed before it.
  void WaitPublished(int64_t generation);

  // Index of the last frame in the published application state of a resumed store (-1: none).
  int64_t resumed_last_index() const;
  // First frame a resumed run must push again (-1: not resuming). The store records every
  // published placement and the optimizer's state (docs/store.md, "Resume record"): frames
  // before this one keep their recorded placement and are not pushed again; from this one to
  // resumed_last_index() they are replayed (re-registered, not painted, nothing published)
  // and keep their recorded placements; newer frames are mosaicked as usual. A store written
  // before the record existed falls back to replaying the last window_frames frames, and
  // resume_warning() says so.
  int64_t resume_replay_from() const;
  // Why this resume cannot reproduce an uninterrupted run ("" when it can).
  const std::string& resume_warning() const;

  MosaickerSummary summary() const;
  // Placement of every frame placed so far (latest estimate, refined by the optimizer). With a
  // store, those of frames that left the optimization window are read back from its frozen
  // frames' file (keep_placements_in_memory), so each call parses the flight so far: for a
  // caller that asks now and then (the end of a run, a report), not per frame. Throws
  // InputError if that file cannot be read.
  std::vector<FramePlacement> Placements() const;
  // Per-frame records as the store keeps them in frames.gpkg (footprint on the mosaic plane,
  // registration quality); empty before the first placed frame.
  std::vector<FrameRecord> FrameRecords() const;
  // Writes the placements JSON (docs/formats.md) that `irmosaic eval` scores.
  void WritePlacements(const std::string& path) const;

  // Painted level-0 extent, mosaic pixels (empty before the first placed frame).
  cv::Rect bounds_px() const;
  // The current mosaic in a level-0 window (as painted, published or not) with its GDAL
  // geotransform and CRS. Throws InputError before the first placed frame or for a window
  // not in 1..65536 pixels a side.
  MosaicWindow ReadWindow(const cv::Rect& mosaic_px) const;
  // The mosaic's georeference (origin, GSD, CRS WKT); known from construction.
  const StoreGeoreference& georeference() const;

  // The store (null before the first placed frame); owned by the Mosaicker. Thread-safe calls
  // only (TileStore documents which).
  TileStore* store();

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace irmosaic
